#pragma once
#include "../Dom/JsonObject.h"
#include "JsonWriter.h"
class FJsonSerializer {
 public:
  template <typename CharType, typename PrintPolicy>
  static bool Serialize(const TSharedRef<FJsonObject>&, const TSharedRef<TJsonWriter<CharType, PrintPolicy>>&) {
    return true;
  }
};
