#pragma once
#include "../UnrealStubs.h"
template <typename CharType> struct TCondensedJsonPrintPolicy {};
template <typename CharType, typename PrintPolicy> class TJsonWriter {};
template <typename CharType, typename PrintPolicy> class TJsonWriterFactory {
 public:
  static TSharedRef<TJsonWriter<CharType, PrintPolicy>> Create(FString*) {
    return MakeShared<TJsonWriter<CharType, PrintPolicy>>();
  }
};
