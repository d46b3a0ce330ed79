#pragma once
#include <map>
#include "../UnrealStubs.h"
// Morph target weights by name, as USkeletalMeshComponent::SetMorphTarget sets them; StubMorphs keeps what was set.
class USkeletalMeshComponent : public UActorComponent {
 public:
  void SetMorphTarget(FName MorphTargetName, float Value, bool bRemoveZeroWeight = true) {
    (void)bRemoveZeroWeight;
    StubMorphs[MorphTargetName] = Value;
  }
  std::map<FName, float> StubMorphs;
};
