// A small, strict JSON reader (RFC 8259) for the protocol: Unity's JsonUtility cannot read nested arrays
// such as "rotations": [[w, x, y, z], ...]. Objects -> Dictionary<string, object>, arrays -> List<object>,
// numbers -> double, plus string, bool and null. Errors say where (line, column) and what was expected.
using System;
using System.Collections.Generic;
using System.Globalization;
using System.Text;

namespace Dimgestor
{
    public static class Json
    {
        const int MaxDepth = 64;  // the protocol nests 4 deep; this only stops hostile input

        public static object Parse(string text)
        {
            if (text == null) throw new ProtocolException("JSON: null text");
            var r = new Reader(text);
            r.SkipWs();
            object v = r.Value(0);
            r.SkipWs();
            if (r.Pos != text.Length) throw r.Error("end of input");
            return v;
        }

        /// <summary>A string as a JSON string literal (quotes, backslashes and control characters escaped).</summary>
        public static string Quote(string s)
        {
            var sb = new StringBuilder("\"");
            foreach (char c in s)
            {
                if (c == '"' || c == '\\') sb.Append('\\').Append(c);
                else if (c < 0x20) sb.Append("\\u").Append(((int)c).ToString("x4", CultureInfo.InvariantCulture));
                else sb.Append(c);
            }
            return sb.Append('"').ToString();
        }

        // ---- typed field access with clear errors

        public static double ToNum(object v, string what)
        {
            if (v is double) return (double)v;
            throw new ProtocolException(what + " is not a number");
        }

        public static double Num(Dictionary<string, object> o, string key, double dflt)
        {
            object v;
            if (!o.TryGetValue(key, out v) || v == null) return dflt;
            return ToNum(v, "\"" + key + "\"");
        }

        public static string Str(Dictionary<string, object> o, string key, string dflt)
        {
            object v;
            if (!o.TryGetValue(key, out v) || v == null) return dflt;
            var s = v as string;
            if (s == null) throw new ProtocolException("\"" + key + "\" is not a string");
            return s;
        }

        public static List<object> Arr(Dictionary<string, object> o, string key)
        {
            object v;
            o.TryGetValue(key, out v);
            var a = v as List<object>;
            if (a == null) throw new ProtocolException("\"" + key + "\" is missing or not an array");
            return a;
        }

        public static Dictionary<string, object> Obj(Dictionary<string, object> o, string key)
        {
            object v;
            o.TryGetValue(key, out v);
            var d = v as Dictionary<string, object>;
            if (d == null) throw new ProtocolException("\"" + key + "\" is missing or not an object");
            return d;
        }

        class Reader
        {
            readonly string s;
            public int Pos;
            public Reader(string text) { s = text; }

            public ProtocolException Error(string expected)
            {
                int line = 1, col = 1;
                for (int i = 0; i < Pos && i < s.Length; i++) { if (s[i] == '\n') { line++; col = 1; } else col++; }
                string found = Pos < s.Length ? "'" + s[Pos] + "'" : "end of input";
                return new ProtocolException("JSON line " + line + " column " + col + ": expected " + expected + ", found " + found);
            }

            public void SkipWs()
            {
                while (Pos < s.Length && (s[Pos] == ' ' || s[Pos] == '\t' || s[Pos] == '\n' || s[Pos] == '\r')) Pos++;
            }

            public object Value(int depth)
            {
                if (depth > MaxDepth) throw Error("less nesting");
                if (Pos >= s.Length) throw Error("a value");
                char c = s[Pos];
                if (c == '{') return Object(depth);
                if (c == '[') return Array(depth);
                if (c == '"') return String();
                if (c == '-' || (c >= '0' && c <= '9')) return Number();
                if (Word("true")) return true;
                if (Word("false")) return false;
                if (Word("null")) return null;
                throw Error("a value");
            }

            bool Word(string w)
            {
                if (string.CompareOrdinal(s, Pos, w, 0, w.Length) != 0) return false;
                Pos += w.Length;
                return true;
            }

            Dictionary<string, object> Object(int depth)
            {
                var o = new Dictionary<string, object>();
                Pos++;  // {
                SkipWs();
                if (Pos < s.Length && s[Pos] == '}') { Pos++; return o; }
                while (true)
                {
                    SkipWs();
                    if (Pos >= s.Length || s[Pos] != '"') throw Error("a string key");
                    string key = String();
                    SkipWs();
                    if (Pos >= s.Length || s[Pos] != ':') throw Error("':'");
                    Pos++;
                    SkipWs();
                    o[key] = Value(depth + 1);  // a repeated key keeps the last value, like most readers
                    SkipWs();
                    if (Pos < s.Length && s[Pos] == ',') { Pos++; continue; }
                    if (Pos < s.Length && s[Pos] == '}') { Pos++; return o; }
                    throw Error("',' or '}'");
                }
            }

            List<object> Array(int depth)
            {
                var a = new List<object>();
                Pos++;  // [
                SkipWs();
                if (Pos < s.Length && s[Pos] == ']') { Pos++; return a; }
                while (true)
                {
                    SkipWs();
                    a.Add(Value(depth + 1));
                    SkipWs();
                    if (Pos < s.Length && s[Pos] == ',') { Pos++; continue; }
                    if (Pos < s.Length && s[Pos] == ']') { Pos++; return a; }
                    throw Error("',' or ']'");
                }
            }

            string String()
            {
                Pos++;  // opening quote
                var sb = new StringBuilder();
                while (true)
                {
                    if (Pos >= s.Length) throw Error("'\"' closing the string");
                    char c = s[Pos++];
                    if (c == '"') return sb.ToString();
                    if (c < 0x20) { Pos--; throw Error("an escaped control character"); }
                    if (c != '\\') { sb.Append(c); continue; }
                    if (Pos >= s.Length) throw Error("an escape");
                    char e = s[Pos++];
                    switch (e)
                    {
                        case '"': sb.Append('"'); break;
                        case '\\': sb.Append('\\'); break;
                        case '/': sb.Append('/'); break;
                        case 'b': sb.Append('\b'); break;
                        case 'f': sb.Append('\f'); break;
                        case 'n': sb.Append('\n'); break;
                        case 'r': sb.Append('\r'); break;
                        case 't': sb.Append('\t'); break;
                        case 'u':  // UTF-16 code unit; surrogate pairs arrive as two escapes and join in the string
                            if (Pos + 4 > s.Length) throw Error("4 hex digits");
                            int code;
                            if (!int.TryParse(s.Substring(Pos, 4), NumberStyles.AllowHexSpecifier, CultureInfo.InvariantCulture, out code))
                                throw Error("4 hex digits");
                            sb.Append((char)code);
                            Pos += 4;
                            break;
                        default: Pos--; throw Error("a valid escape");
                    }
                }
            }

            double Number()
            {
                int start = Pos;
                if (s[Pos] == '-') Pos++;
                if (Pos < s.Length && s[Pos] == '0') Pos++;
                else if (!Digits()) throw Error("a digit");
                if (Pos < s.Length && s[Pos] == '.') { Pos++; if (!Digits()) throw Error("a digit after '.'"); }
                if (Pos < s.Length && (s[Pos] == 'e' || s[Pos] == 'E'))
                {
                    Pos++;
                    if (Pos < s.Length && (s[Pos] == '+' || s[Pos] == '-')) Pos++;
                    if (!Digits()) throw Error("an exponent");
                }
                // Invariant culture: a German locale would otherwise read "0,5"-style numbers.
                return double.Parse(s.Substring(start, Pos - start), NumberStyles.Float, CultureInfo.InvariantCulture);
            }

            bool Digits()
            {
                int start = Pos;
                while (Pos < s.Length && s[Pos] >= '0' && s[Pos] <= '9') Pos++;
                return Pos > start;
            }
        }
    }
}
