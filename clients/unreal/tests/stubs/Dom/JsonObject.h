#pragma once
#include <utility>
#include <vector>
#include "../UnrealStubs.h"
// Keeps its string fields (and says how many of the others it has), so tests can tell messages apart.
class FJsonObject {
 public:
  void SetStringField(const FString& k, const FString& v) { StubStrings.emplace_back(k, v); }
  void SetNumberField(const FString&, double) { ++StubOthers; }
  void SetObjectField(const FString&, const TSharedPtr<FJsonObject>&) { ++StubOthers; }
  std::vector<std::pair<FString, FString>> StubStrings;
  int StubOthers = 0;
};
