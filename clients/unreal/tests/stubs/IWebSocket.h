#pragma once
#include <cstring>
#include <functional>
#include <string>
#include "UnrealStubs.h"
// Multicast events as IWebSocket exposes them (AddUObject(object, &Class::Handler), RemoveAll(object));
// StubBroadcast lets a test play the server's part.
template <typename... Args> class TWebSocketEventStub {
 public:
  template <typename U> void AddUObject(U* Object, void (U::*Handler)(Args...)) {
    handlers_.push_back([Object, Handler](Args... a) { (Object->*Handler)(a...); });
  }
  void RemoveAll(const void*) { handlers_.clear(); }
  void StubBroadcast(Args... a) { for (auto& h : handlers_) h(a...); }
 private:
  std::vector<std::function<void(Args...)>> handlers_;
};
class IWebSocket {
 public:
  virtual ~IWebSocket() = default;
  void Connect() {}
  void Close(int32 Code = 1000, const FString& Reason = FString()) { (void)Code; (void)Reason; }
  bool IsConnected() { return StubConnected; }
  void Send(const FString& Text) {
    StubSentText.push_back(Text);
    std::wstring w(*Text);
    StubSent.push_back("text:" + std::string(w.begin(), w.end()));
  }
  void Send(const void* Data, SIZE_T Size, bool bIsBinary = false) {  // logged as binary:FIRST_FLOAT:BYTES
    float first = 0;
    if (Size >= sizeof first) std::memcpy(&first, Data, sizeof first);
    StubSent.push_back((bIsBinary ? "binary:" : "text?:") + std::to_string(int(first)) + ":" + std::to_string(Size));
  }
  TWebSocketEventStub<>& OnConnected() { return connected_; }
  TWebSocketEventStub<const FString&>& OnConnectionError() { return error_; }
  TWebSocketEventStub<int32, const FString&, bool>& OnClosed() { return closed_; }
  TWebSocketEventStub<const FString&>& OnMessage() { return message_; }
  TWebSocketEventStub<const void*, SIZE_T, bool>& OnBinaryMessage() { return binary_; }
  bool StubConnected = false;
  std::vector<FString> StubSentText;
  std::vector<std::string> StubSent;  // every send in order (text and binary)
 private:
  TWebSocketEventStub<> connected_;
  TWebSocketEventStub<const FString&> error_;
  TWebSocketEventStub<int32, const FString&, bool> closed_;
  TWebSocketEventStub<const FString&> message_;
  TWebSocketEventStub<const void*, SIZE_T, bool> binary_;
};
