// A small strict JSON reader (RFC 8259) for the protocol, standard library only and without exceptions,
// so DimgestorProtocol compiles inside Unreal and anywhere else. Errors give line and column.
#pragma once

#include <string>
#include <vector>

namespace dimgestor {

struct JsonValue {
  enum Kind { Null, Bool, Number, String, Array, Object } kind = Null;
  bool b = false;
  double n = 0;
  std::string s;                  // String (UTF-8)
  std::vector<JsonValue> items;   // Array elements, or Object values
  std::vector<std::string> keys;  // Object keys, parallel to items

  // The value of `key` in an Object (the last one if repeated), or nullptr.
  const JsonValue* Get(const std::string& key) const;
};

// Parse JSON text into `out`; on bad input returns false and says what and where in `error`.
bool ParseJson(const std::string& text, JsonValue& out, std::string& error);

}  // namespace dimgestor
