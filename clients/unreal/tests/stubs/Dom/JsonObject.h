#pragma once
#include "../UnrealStubs.h"
class FJsonObject {
 public:
  void SetStringField(const FString&, const FString&) {}
  void SetNumberField(const FString&, double) {}
  void SetObjectField(const FString&, const TSharedPtr<FJsonObject>&) {}
};
