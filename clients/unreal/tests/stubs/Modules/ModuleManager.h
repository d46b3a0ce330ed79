#pragma once
#include "../UnrealStubs.h"
class FModuleManager {
 public:
  static FModuleManager& Get() { static FModuleManager m; return m; }
  template <typename T> static T& LoadModuleChecked(const TCHAR*) { static T m; return m; }
};
