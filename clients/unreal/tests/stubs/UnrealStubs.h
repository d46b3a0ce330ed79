// Stand-ins for the few Unreal Engine types DimgestorComponent uses, with the engine's names and call
// shapes, so g++ can type-check the component outside the engine, plus just enough behaviour (quaternion
// and rotator maths, a bone hierarchy, WebSocket events the test can fire) for the retarget test
// (retarget_check.cpp). Members named Stub* exist only here. Never part of a game build.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cwctype>
#include <map>
#include <memory>
#include <string>
#include <vector>

#define UCLASS(...)
#define UPROPERTY(...)
#define UFUNCTION(...)
#define TEXT(x) L##x
#define UTF8_TO_TCHAR(s) (::ue_stub::Widen(s).c_str())

using int32 = int32_t;
using int64 = int64_t;
using uint8 = uint8_t;
using SIZE_T = size_t;
using TCHAR = wchar_t;
using ANSICHAR = char;
constexpr int32 INDEX_NONE = -1;

namespace ue_stub {
inline std::wstring Widen(const char* s) { return std::wstring(s, s + std::char_traits<char>::length(s)); }
}

class FString {
 public:
  FString() = default;
  FString(const TCHAR* s) : s_(s) {}
  const TCHAR* operator*() const { return s_.c_str(); }
  bool IsEmpty() const { return s_.empty(); }
  bool Contains(const TCHAR* sub) const { return s_.find(sub) != std::wstring::npos; }
  void AppendChar(TCHAR c) { s_ += c; }
  FString& operator+=(const FString& o) { s_ += o.s_; return *this; }
  friend FString operator+(const FString& a, const FString& b) { FString r = a; r += b; return r; }
  friend FString operator+(const TCHAR* a, const FString& b) { return FString(a) + b; }
  friend FString operator+(const FString& a, const TCHAR* b) { return a + FString(b); }
  bool operator<(const FString& o) const { return s_ < o.s_; }
  template <typename... A> static FString Printf(const TCHAR* fmt, A...) { return FString(fmt); }
 private:
  std::wstring s_;
};

class FName {
 public:
  FName() = default;
  FName(const TCHAR* s) : s_(s) {}
  bool operator==(const FName& o) const { return s_ == o.s_; }
  bool operator!=(const FName& o) const { return s_ != o.s_; }
  bool operator<(const FName& o) const { return s_ < o.s_; }
  FString ToString() const { return FString(s_.c_str()); }
 private:
  std::wstring s_;
};
static const FName NAME_None;

struct FPlatformTime {
  static double& StubNow() { static double now = 0; return now; }  // the test sets the clock
  static double Seconds() { return StubNow(); }
};

struct FChar { static bool IsAlnum(TCHAR c) { return std::iswalnum(c) != 0; } };

class FTCHARToUTF8 {
 public:
  explicit FTCHARToUTF8(const TCHAR* s) { for (; *s; ++s) u_ += char(*s); }
  const ANSICHAR* Get() const { return u_.c_str(); }
  int32 Length() const { return int32(u_.size()); }
 private:
  std::string u_;
};

template <typename T> class TArray {
 public:
  void Add(const T& v) { v_.push_back(v); }
  void Append(const T* p, SIZE_T n) { v_.insert(v_.end(), p, p + n); }
  int32 Num() const { return int32(v_.size()); }
  T& operator[](int32 i) { return v_[size_t(i)]; }
  const T& operator[](int32 i) const { return v_[size_t(i)]; }
  T* GetData() { return v_.data(); }
  const T* GetData() const { return v_.data(); }
  void Reset() { v_.clear(); }
  template <typename P> void Sort(P pred) { std::sort(v_.begin(), v_.end(), pred); }
  typename std::vector<T>::iterator begin() { return v_.begin(); }
  typename std::vector<T>::iterator end() { return v_.end(); }
  typename std::vector<T>::const_iterator begin() const { return v_.begin(); }
  typename std::vector<T>::const_iterator end() const { return v_.end(); }
 private:
  std::vector<T> v_;
};

template <typename K, typename V> class TMap {
 public:
  void Add(const K& k, const V& v) { m_[k] = v; }
  V* Find(const K& k) { auto it = m_.find(k); return it == m_.end() ? nullptr : &it->second; }
  const V* Find(const K& k) const { auto it = m_.find(k); return it == m_.end() ? nullptr : &it->second; }
  V& operator[](const K& k) { return m_[k]; }
  int32 Num() const { return int32(m_.size()); }
 private:
  std::map<K, V> m_;
};

template <typename T> class TSharedPtr : public std::shared_ptr<T> {
 public:
  TSharedPtr() = default;
  TSharedPtr(const std::shared_ptr<T>& p) : std::shared_ptr<T>(p) {}
  void Reset() { this->reset(); }
};
template <typename T> class TSharedRef : public std::shared_ptr<T> {
 public:
  explicit TSharedRef(const std::shared_ptr<T>& p) : std::shared_ptr<T>(p) {}
};
template <typename T, typename... A> TSharedRef<T> MakeShared(A&&... a) { return TSharedRef<T>(std::make_shared<T>(a...)); }
template <typename T> using TObjectPtr = T*;

struct FVector {
  double X = 0, Y = 0, Z = 0;
  FVector() = default;
  FVector(double x, double y, double z) : X(x), Y(y), Z(z) {}
  static const FVector ZeroVector;
  FVector operator+(const FVector& o) const { return {X + o.X, Y + o.Y, Z + o.Z}; }
  FVector operator-(const FVector& o) const { return {X - o.X, Y - o.Y, Z - o.Z}; }
  FVector operator*(float s) const { return {X * s, Y * s, Z * s}; }
  double SizeSquared() const { return X * X + Y * Y + Z * Z; }
};
inline const FVector FVector::ZeroVector{};

struct FQuat {
  double X = 0, Y = 0, Z = 0, W = 1;
  FQuat() = default;
  FQuat(double x, double y, double z, double w) : X(x), Y(y), Z(z), W(w) {}
  static const FQuat Identity;
  static FQuat FindBetweenVectors(const FVector& a, const FVector& b) {  // the engine's formula
    const double norm = std::sqrt(a.SizeSquared() * b.SizeSquared()), w = norm + a.X * b.X + a.Y * b.Y + a.Z * b.Z;
    const FQuat q = w >= 1e-6 * norm ? FQuat(a.Y * b.Z - a.Z * b.Y, a.Z * b.X - a.X * b.Z, a.X * b.Y - a.Y * b.X, w)
                    : std::abs(a.X) > std::abs(a.Y) ? FQuat(-a.Z, 0, a.X, 0) : FQuat(0, -a.Z, a.Y, 0);  // opposite
    return q.GetNormalized();
  }
  FQuat operator*(const FQuat& b) const {  // apply b first, then this (as in the engine)
    return {W * b.X + X * b.W + Y * b.Z - Z * b.Y, W * b.Y - X * b.Z + Y * b.W + Z * b.X,
            W * b.Z + X * b.Y - Y * b.X + Z * b.W, W * b.W - X * b.X - Y * b.Y - Z * b.Z};
  }
  FQuat Inverse() const { return {-X, -Y, -Z, W}; }
  FQuat GetNormalized() const {
    double n = std::sqrt(X * X + Y * Y + Z * Z + W * W);
    return {X / n, Y / n, Z / n, W / n};
  }
  FVector RotateVector(const FVector& v) const {
    FQuat r = *this * FQuat(v.X, v.Y, v.Z, 0) * Inverse();
    return {r.X, r.Y, r.Z};
  }
};
inline const FQuat FQuat::Identity{};

struct FRotator {
  double Pitch = 0, Yaw = 0, Roll = 0;
  FRotator() = default;
  FRotator(double p, double y, double r) : Pitch(p), Yaw(y), Roll(r) {}
  FQuat Quaternion() const {  // the engine's FRotator -> FQuat formula (degrees)
    const double d = 3.14159265358979323846 / 360.0;
    const double SP = std::sin(Pitch * d), CP = std::cos(Pitch * d), SY = std::sin(Yaw * d), CY = std::cos(Yaw * d);
    const double SR = std::sin(Roll * d), CR = std::cos(Roll * d);
    return {CR * SP * SY - SR * CP * CY, -CR * SP * CY - SR * CP * SY, CR * CP * SY - SR * SP * CY,
            CR * CP * CY + SR * SP * SY};
  }
};

struct FTransform {
  FTransform() = default;
  FTransform(const FQuat& r, const FVector& t) : R(r), T(t) {}
  FQuat GetRotation() const { return R; }
  void SetRotation(const FQuat& q) { R = q; }
  FVector GetLocation() const { return T; }
  void SetLocation(const FVector& v) { T = v; }
  FQuat R;
  FVector T;
};

namespace EBoneSpaces { enum Type { WorldSpace, ComponentSpace }; }
namespace EEndPlayReason { enum Type { Destroyed, LevelTransition, EndPlayInEditor, RemovedFromWorld, Quit }; }
enum ELevelTick { LEVELTICK_TimeOnly, LEVELTICK_ViewportsOnly, LEVELTICK_All, LEVELTICK_PauseTick };
enum ETickingGroup { TG_PrePhysics, TG_DuringPhysics, TG_PostPhysics, TG_PostUpdateWork };
struct FActorComponentTickFunction { bool bCanEverTick = false; ETickingGroup TickGroup = TG_DuringPhysics; };

class UObject { public: virtual ~UObject() = default; };
class UActorComponent;
class AActor : public UObject {
 public:
  template <typename T> T* FindComponentByClass() const { return nullptr; }
};
class UActorComponent : public UObject {
 public:
  FActorComponentTickFunction PrimaryComponentTick;
  AActor* GetOwner() const { return nullptr; }
  virtual void BeginPlay() {}
  virtual void EndPlay(const EEndPlayReason::Type) {}
  virtual void TickComponent(float, ELevelTick, FActorComponentTickFunction*) {}
};
