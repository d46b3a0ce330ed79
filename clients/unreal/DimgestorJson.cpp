// A small strict JSON reader; see DimgestorJson.h.
#include "DimgestorJson.h"

#include <cstdint>
#include <cstring>
#include <locale>
#include <sstream>
#if defined(__has_include)
#if __has_include(<charconv>)
#include <charconv>
#endif
#endif

namespace dimgestor {

const JsonValue* JsonValue::Get(const std::string& key) const {
  for (size_t i = keys.size(); i-- > 0;)  // last wins for repeated keys
    if (keys[i] == key) return &items[i];
  return nullptr;
}

namespace {

class JsonReader {
 public:
  explicit JsonReader(const std::string& text) : s_(text) {}

  bool Parse(JsonValue& out, std::string& error) {
    SkipWs();
    if (!Value(out, 0)) { error = error_; return false; }
    SkipWs();
    if (pos_ != s_.size()) { Fail("end of input"); error = error_; return false; }
    return true;
  }

 private:
  static constexpr int kMaxDepth = 64;  // the protocol nests 4 deep; this only stops hostile input
  const std::string& s_;
  size_t pos_ = 0;
  std::string error_;

  bool Fail(const char* expected) {
    size_t line = 1, col = 1;
    for (size_t i = 0; i < pos_ && i < s_.size(); ++i) {
      if (s_[i] == '\n') { ++line; col = 1; } else { ++col; }
    }
    std::string found = pos_ < s_.size() ? std::string("'") + s_[pos_] + "'" : "end of input";
    error_ = "JSON line " + std::to_string(line) + " column " + std::to_string(col) + ": expected " + expected +
             ", found " + found;
    return false;
  }
  bool At(char c) const { return pos_ < s_.size() && s_[pos_] == c; }
  void SkipWs() {
    while (pos_ < s_.size() && (s_[pos_] == ' ' || s_[pos_] == '\t' || s_[pos_] == '\n' || s_[pos_] == '\r')) ++pos_;
  }
  bool Word(const char* w) {
    size_t n = std::strlen(w);
    if (s_.compare(pos_, n, w) != 0) return false;
    pos_ += n;
    return true;
  }

  bool Value(JsonValue& v, int depth) {
    if (depth > kMaxDepth) return Fail("less nesting");
    if (pos_ >= s_.size()) return Fail("a value");
    char c = s_[pos_];
    if (c == '{') return ObjectValue(v, depth);
    if (c == '[') return ArrayValue(v, depth);
    if (c == '"') { v.kind = JsonValue::String; return StringValue(v.s); }
    if (c == '-' || (c >= '0' && c <= '9')) { v.kind = JsonValue::Number; return NumberValue(v.n); }
    if (Word("true")) { v.kind = JsonValue::Bool; v.b = true; return true; }
    if (Word("false")) { v.kind = JsonValue::Bool; v.b = false; return true; }
    if (Word("null")) { v.kind = JsonValue::Null; return true; }
    return Fail("a value");
  }

  bool ObjectValue(JsonValue& v, int depth) {
    v.kind = JsonValue::Object;
    ++pos_;
    SkipWs();
    if (At('}')) { ++pos_; return true; }
    for (;;) {
      SkipWs();
      if (!At('"')) return Fail("a string key");
      v.keys.emplace_back();
      if (!StringValue(v.keys.back())) return false;
      SkipWs();
      if (!At(':')) return Fail("':'");
      ++pos_;
      SkipWs();
      v.items.emplace_back();
      if (!Value(v.items.back(), depth + 1)) return false;
      SkipWs();
      if (At(',')) { ++pos_; continue; }
      if (At('}')) { ++pos_; return true; }
      return Fail("',' or '}'");
    }
  }

  bool ArrayValue(JsonValue& v, int depth) {
    v.kind = JsonValue::Array;
    ++pos_;
    SkipWs();
    if (At(']')) { ++pos_; return true; }
    for (;;) {
      SkipWs();
      v.items.emplace_back();
      if (!Value(v.items.back(), depth + 1)) return false;
      SkipWs();
      if (At(',')) { ++pos_; continue; }
      if (At(']')) { ++pos_; return true; }
      return Fail("',' or ']'");
    }
  }

  static void AppendUtf8(std::string& out, uint32_t cp) {
    if (cp < 0x80) { out += char(cp); }
    else if (cp < 0x800) { out += char(0xC0 | (cp >> 6)); out += char(0x80 | (cp & 0x3F)); }
    else if (cp < 0x10000) {
      out += char(0xE0 | (cp >> 12)); out += char(0x80 | ((cp >> 6) & 0x3F)); out += char(0x80 | (cp & 0x3F));
    } else {
      out += char(0xF0 | (cp >> 18)); out += char(0x80 | ((cp >> 12) & 0x3F));
      out += char(0x80 | ((cp >> 6) & 0x3F)); out += char(0x80 | (cp & 0x3F));
    }
  }

  bool Hex4(uint32_t& cp) {
    if (pos_ + 4 > s_.size()) return Fail("4 hex digits");
    cp = 0;
    for (int i = 0; i < 4; ++i) {
      char c = s_[pos_ + i];
      int d = (c >= '0' && c <= '9') ? c - '0' : (c >= 'a' && c <= 'f') ? c - 'a' + 10 : (c >= 'A' && c <= 'F') ? c - 'A' + 10 : -1;
      if (d < 0) return Fail("4 hex digits");
      cp = cp * 16 + uint32_t(d);
    }
    pos_ += 4;
    return true;
  }

  bool StringValue(std::string& out) {
    ++pos_;  // opening quote
    for (;;) {
      if (pos_ >= s_.size()) return Fail("'\"' closing the string");
      char c = s_[pos_++];
      if (c == '"') return true;
      if (static_cast<unsigned char>(c) < 0x20) { --pos_; return Fail("an escaped control character"); }
      if (c != '\\') { out += c; continue; }  // UTF-8 bytes pass through unchanged
      if (pos_ >= s_.size()) return Fail("an escape");
      char e = s_[pos_++];
      switch (e) {
        case '"': out += '"'; break;
        case '\\': out += '\\'; break;
        case '/': out += '/'; break;
        case 'b': out += '\b'; break;
        case 'f': out += '\f'; break;
        case 'n': out += '\n'; break;
        case 'r': out += '\r'; break;
        case 't': out += '\t'; break;
        case 'u': {
          uint32_t cp = 0;
          if (!Hex4(cp)) return false;
          if (cp >= 0xD800 && cp < 0xDC00 && s_.compare(pos_, 2, "\\u") == 0) {  // surrogate pair
            pos_ += 2;
            uint32_t lo = 0;
            if (!Hex4(lo)) return false;
            if (lo >= 0xDC00 && lo < 0xE000) cp = 0x10000 + ((cp - 0xD800) << 10) + (lo - 0xDC00);
            else { AppendUtf8(out, cp); cp = lo; }  // unpaired: keep both code units
          }
          AppendUtf8(out, cp);
          break;
        }
        default: --pos_; return Fail("a valid escape");
      }
    }
  }

  bool Digits() {
    size_t start = pos_;
    while (pos_ < s_.size() && s_[pos_] >= '0' && s_[pos_] <= '9') ++pos_;
    return pos_ > start;
  }

  bool NumberValue(double& out) {
    size_t start = pos_;
    if (At('-')) ++pos_;
    if (At('0')) ++pos_;
    else if (!Digits()) return Fail("a digit");
    if (At('.')) { ++pos_; if (!Digits()) return Fail("a digit after '.'"); }
    if (At('e') || At('E')) {
      ++pos_;
      if (At('+') || At('-')) ++pos_;
      if (!Digits()) return Fail("an exponent");
    }
    // Locale-independent and correctly rounded: strtod would read "0.5" wrongly under a German locale.
#if defined(__cpp_lib_to_chars) && __cpp_lib_to_chars >= 201611L
    auto r = std::from_chars(s_.data() + start, s_.data() + pos_, out);
    if (r.ec != std::errc() && r.ec != std::errc::result_out_of_range) { pos_ = start; return Fail("a number"); }
#else
    std::istringstream in(s_.substr(start, pos_ - start));
    in.imbue(std::locale::classic());
    in >> out;
    if (in.fail()) { pos_ = start; return Fail("a number"); }
#endif
    return true;
  }
};

}  // namespace

bool ParseJson(const std::string& text, JsonValue& out, std::string& error) {
  JsonReader reader(text);
  return reader.Parse(out, error);
}

}  // namespace dimgestor
