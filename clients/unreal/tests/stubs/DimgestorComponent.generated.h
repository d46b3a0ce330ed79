// Stand-in for the header UnrealHeaderTool generates; GENERATED_BODY gives the class its `Super`.
#pragma once
#define GENERATED_BODY() \
 public:                 \
  typedef UActorComponent Super;
