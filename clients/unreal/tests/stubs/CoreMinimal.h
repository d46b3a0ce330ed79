#pragma once
#include "UnrealStubs.h"
