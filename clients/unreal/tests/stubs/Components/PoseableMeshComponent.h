#pragma once
#include "../UnrealStubs.h"
// Bones with parents and local (parent-space) transforms, rotation and translation only.
class UPoseableMeshComponent : public UActorComponent {
 public:
  int32 GetNumBones() const { return int32(StubNames.size()); }
  FName GetBoneName(int32 i) const { return StubNames[size_t(i)]; }
  FTransform GetBoneTransformByName(FName Bone, EBoneSpaces::Type) {
    int32 i = StubIndex(Bone);
    if (i < 0) return FTransform();
    FTransform local = StubLocal[size_t(i)];
    if (StubParents[size_t(i)] < 0) return local;
    FTransform parent = GetBoneTransformByName(StubNames[size_t(StubParents[size_t(i)])], EBoneSpaces::ComponentSpace);
    return FTransform(parent.R * local.R, parent.T + parent.R.RotateVector(local.T));
  }
  void SetBoneTransformByName(FName Bone, const FTransform& T, EBoneSpaces::Type) {
    int32 i = StubIndex(Bone);
    if (i < 0) return;
    if (StubParents[size_t(i)] < 0) { StubLocal[size_t(i)] = T; return; }
    FTransform parent = GetBoneTransformByName(StubNames[size_t(StubParents[size_t(i)])], EBoneSpaces::ComponentSpace);
    FQuat inv = parent.R.Inverse();
    StubLocal[size_t(i)] = FTransform(inv * T.R, inv.RotateVector(T.T - parent.T));
  }
  int32 StubIndex(FName Bone) const {
    for (size_t i = 0; i < StubNames.size(); ++i)
      if (StubNames[i] == Bone) return int32(i);
    return -1;
  }
  std::vector<FName> StubNames;
  std::vector<int32> StubParents;
  std::vector<FTransform> StubLocal;
};
