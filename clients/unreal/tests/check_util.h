// Shared by the component test drivers: strings between the stand-ins' FString and JSON output, and a
// one-bone mesh to hang a UDimgestorComponent on.
#pragma once
#include <string>

#include "Components/PoseableMeshComponent.h"

inline FString Wide(const std::string& s) { std::wstring w(s.begin(), s.end()); return FString(w.c_str()); }
inline std::string Narrow(const FString& s) { std::wstring w(*s); return std::string(w.begin(), w.end()); }
inline std::string Quoted(const std::string& s) {
  std::string o = "\"";
  for (char c : s) { if (c == '"' || c == '\\') o += '\\'; o += c; }
  return o + "\"";
}
inline void OneBoneMesh(UPoseableMeshComponent& mesh) {
  mesh.StubNames.push_back(FName(TEXT("root")));
  mesh.StubParents.push_back(-1);
  mesh.StubLocal.emplace_back();
}
