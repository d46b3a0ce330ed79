#pragma once
#include "UnrealStubs.h"
// Multicast events as IWebSocket exposes them: AddUObject(object, &Class::Handler), RemoveAll(object).
template <typename... Args> class TWebSocketEventStub {
 public:
  template <typename U> void AddUObject(U*, void (U::*)(Args...)) {}
  void RemoveAll(const void*) {}
};
class IWebSocket {
 public:
  virtual ~IWebSocket() = default;
  void Connect() {}
  void Close(int32 Code = 1000, const FString& Reason = FString()) {}
  bool IsConnected() { return false; }
  void Send(const FString&) {}
  void Send(const void*, SIZE_T, bool bIsBinary = false) {}
  TWebSocketEventStub<>& OnConnected() { return connected_; }
  TWebSocketEventStub<const FString&>& OnConnectionError() { return error_; }
  TWebSocketEventStub<int32, const FString&, bool>& OnClosed() { return closed_; }
  TWebSocketEventStub<const FString&>& OnMessage() { return message_; }
  TWebSocketEventStub<const void*, SIZE_T, bool>& OnBinaryMessage() { return binary_; }
 private:
  TWebSocketEventStub<> connected_;
  TWebSocketEventStub<const FString&> error_;
  TWebSocketEventStub<int32, const FString&, bool> closed_;
  TWebSocketEventStub<const FString&> message_;
  TWebSocketEventStub<const void*, SIZE_T, bool> binary_;
};
