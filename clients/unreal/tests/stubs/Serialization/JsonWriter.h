#pragma once
#include "../UnrealStubs.h"
template <typename CharType> struct TCondensedJsonPrintPolicy {};
template <typename CharType, typename PrintPolicy> class TJsonWriter {
 public:
  explicit TJsonWriter(FString* out) : StubOut(out) {}
  FString* StubOut;
};
template <typename CharType, typename PrintPolicy> class TJsonWriterFactory {
 public:
  static TSharedRef<TJsonWriter<CharType, PrintPolicy>> Create(FString* out) {
    return MakeShared<TJsonWriter<CharType, PrintPolicy>>(out);
  }
};
