#pragma once
#include "IWebSocket.h"
class FWebSocketsModule {
 public:
  static FWebSocketsModule& Get() { static FWebSocketsModule m; return m; }
  TSharedRef<IWebSocket> CreateWebSocket(const FString& Url, const FString& Protocol = FString()) {
    StubUrl = Url;
    (void)Protocol;
    TSharedRef<IWebSocket> Socket = MakeShared<IWebSocket>();
    StubLast = Socket;
    return Socket;
  }
  FString StubUrl;
  TSharedPtr<IWebSocket> StubLast;  // the socket the component made, for the test to drive
};
