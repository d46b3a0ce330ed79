#pragma once
#include "../UnrealStubs.h"
class UPoseableMeshComponent : public UActorComponent {
 public:
  int32 GetNumBones() const { return 0; }
  FName GetBoneName(int32) const { return FName(); }
  FTransform GetBoneTransformByName(FName, EBoneSpaces::Type) { return FTransform(); }
  void SetBoneTransformByName(FName, const FTransform&, EBoneSpaces::Type) {}
};
