#pragma once
#include "../Dom/JsonObject.h"
#include "JsonWriter.h"
// Writes the string fields only ({"type":"hello",...}): enough for a test to tell messages apart.
class FJsonSerializer {
 public:
  template <typename CharType, typename PrintPolicy>
  static bool Serialize(const TSharedRef<FJsonObject>& o, const TSharedRef<TJsonWriter<CharType, PrintPolicy>>& w) {
    FString s(TEXT("{"));
    bool first = true;
    for (const auto& kv : o->StubStrings) {
      s += FString(first ? TEXT("\"") : TEXT(",\"")) + kv.first + TEXT("\":\"") + kv.second + TEXT("\"");
      first = false;
    }
    *w->StubOut = s + TEXT("}");
    return true;
  }
};
