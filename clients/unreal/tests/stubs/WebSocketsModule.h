#pragma once
#include "IWebSocket.h"
class FWebSocketsModule {
 public:
  static FWebSocketsModule& Get() { static FWebSocketsModule m; return m; }
  TSharedRef<IWebSocket> CreateWebSocket(const FString& Url, const FString& Protocol = FString()) {
    return MakeShared<IWebSocket>();
  }
};
