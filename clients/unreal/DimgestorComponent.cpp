// Retargeting: the server skeleton and the mesh have different bone axes and may have different rest poses, so
// local rotations cannot be copied. For each bound bone we take the source joint's global rotation relative to the
// source rest (delta = G_frame * G_rest^-1, converted to Unreal axes, then into component space by
// SourceToComponent C) and put it on top of the bone's own reference pose, first aligned onto the source rest:
// R_component = C * delta * C^-1 * A * R_rest_component. A turns the mesh's reference bone (bone -> its bound child)
// onto the source skeleton's rest bone between the same joints, so any reference pose works (T or A, e.g. the UE5
// Mannequin's); a bone without a bound child turns with its parent.
#include "DimgestorComponent.h"

#include <algorithm>
#include <set>

#include "Components/PoseableMeshComponent.h"
#include "Components/SkeletalMeshComponent.h"
#include "Dom/JsonObject.h"
#include "IWebSocket.h"
#include "Modules/ModuleManager.h"
#include "Serialization/JsonSerializer.h"
#include "Serialization/JsonWriter.h"
#include "WebSocketsModule.h"

namespace
{
// Unity HumanBodyBones name -> UE5 Mannequin (SK_Mannequin / Manny, Quinn) bone.
const TCHAR* const GMannequinBones[][2] = {
	{TEXT("Hips"), TEXT("pelvis")}, {TEXT("Spine"), TEXT("spine_01")}, {TEXT("Chest"), TEXT("spine_03")},
	{TEXT("UpperChest"), TEXT("spine_05")}, {TEXT("Neck"), TEXT("neck_01")}, {TEXT("Head"), TEXT("head")},
	{TEXT("LeftShoulder"), TEXT("clavicle_l")}, {TEXT("LeftUpperArm"), TEXT("upperarm_l")},
	{TEXT("LeftLowerArm"), TEXT("lowerarm_l")}, {TEXT("LeftHand"), TEXT("hand_l")},
	{TEXT("RightShoulder"), TEXT("clavicle_r")}, {TEXT("RightUpperArm"), TEXT("upperarm_r")},
	{TEXT("RightLowerArm"), TEXT("lowerarm_r")}, {TEXT("RightHand"), TEXT("hand_r")},
	{TEXT("LeftUpperLeg"), TEXT("thigh_l")}, {TEXT("LeftLowerLeg"), TEXT("calf_l")}, {TEXT("LeftFoot"), TEXT("foot_l")},
	{TEXT("LeftToes"), TEXT("ball_l")}, {TEXT("RightUpperLeg"), TEXT("thigh_r")}, {TEXT("RightLowerLeg"), TEXT("calf_r")},
	{TEXT("RightFoot"), TEXT("foot_r")}, {TEXT("RightToes"), TEXT("ball_r")},
	{TEXT("LeftThumbProximal"), TEXT("thumb_01_l")}, {TEXT("LeftThumbIntermediate"), TEXT("thumb_02_l")},
	{TEXT("LeftThumbDistal"), TEXT("thumb_03_l")}, {TEXT("LeftIndexProximal"), TEXT("index_01_l")},
	{TEXT("LeftIndexIntermediate"), TEXT("index_02_l")}, {TEXT("LeftIndexDistal"), TEXT("index_03_l")},
	{TEXT("LeftMiddleProximal"), TEXT("middle_01_l")}, {TEXT("LeftMiddleIntermediate"), TEXT("middle_02_l")},
	{TEXT("LeftMiddleDistal"), TEXT("middle_03_l")}, {TEXT("LeftRingProximal"), TEXT("ring_01_l")},
	{TEXT("LeftRingIntermediate"), TEXT("ring_02_l")}, {TEXT("LeftRingDistal"), TEXT("ring_03_l")},
	{TEXT("LeftLittleProximal"), TEXT("pinky_01_l")}, {TEXT("LeftLittleIntermediate"), TEXT("pinky_02_l")},
	{TEXT("LeftLittleDistal"), TEXT("pinky_03_l")},
	{TEXT("RightThumbProximal"), TEXT("thumb_01_r")}, {TEXT("RightThumbIntermediate"), TEXT("thumb_02_r")},
	{TEXT("RightThumbDistal"), TEXT("thumb_03_r")}, {TEXT("RightIndexProximal"), TEXT("index_01_r")},
	{TEXT("RightIndexIntermediate"), TEXT("index_02_r")}, {TEXT("RightIndexDistal"), TEXT("index_03_r")},
	{TEXT("RightMiddleProximal"), TEXT("middle_01_r")}, {TEXT("RightMiddleIntermediate"), TEXT("middle_02_r")},
	{TEXT("RightMiddleDistal"), TEXT("middle_03_r")}, {TEXT("RightRingProximal"), TEXT("ring_01_r")},
	{TEXT("RightRingIntermediate"), TEXT("ring_02_r")}, {TEXT("RightRingDistal"), TEXT("ring_03_r")},
	{TEXT("RightLittleProximal"), TEXT("pinky_01_r")}, {TEXT("RightLittleIntermediate"), TEXT("pinky_02_r")},
	{TEXT("RightLittleDistal"), TEXT("pinky_03_r")},
};

// Where a humanoid bone points: towards the first of these children the skeleton has, else its first bound child.
const std::map<std::string, std::vector<std::string>> GDirectionChildren = {
	{"Hips", {"Spine"}}, {"Spine", {"Chest", "UpperChest", "Neck"}}, {"Chest", {"UpperChest", "Neck"}},
	{"UpperChest", {"Neck"}}, {"Neck", {"Head"}},
	{"LeftHand", {"LeftMiddleProximal", "LeftIndexProximal"}}, {"RightHand", {"RightMiddleProximal", "RightIndexProximal"}},
};
const std::set<std::string> GNotDirections = {"Jaw", "LeftEye", "RightEye"};  // children that do not say where a bone points
constexpr double MinBoneCm = 0.01;  // shorter bones have no direction to align

FQuat ToFQuat(const dimgestor::Quat& Q) { return FQuat(Q.x, Q.y, Q.z, Q.w); }  // FQuat takes (X, Y, Z, W)

// The server skeleton's rest joint locations in component space (Unreal axes, cm, turned by C).
std::vector<FVector> SourceRestLocations(const dimgestor::Skeleton& S, const std::vector<dimgestor::Quat>& RestGlobal, const FQuat& C)
{
	std::vector<dimgestor::Vec3> P(S.joints.size());
	std::vector<FVector> Out(S.joints.size());
	for (size_t j = 0; j < S.joints.size(); ++j)
	{
		P[j] = S.offsets[j];
		if (S.parents[j] >= 0)
		{
			const dimgestor::Quat& G = RestGlobal[size_t(S.parents[j])];
			const dimgestor::Quat V = G * dimgestor::Quat{0, S.offsets[j].x, S.offsets[j].y, S.offsets[j].z} * dimgestor::Conjugate(G);
			const dimgestor::Vec3& Q = P[size_t(S.parents[j])];
			P[j] = dimgestor::Vec3{Q.x + V.x, Q.y + V.y, Q.z + V.z};
		}
		const dimgestor::Vec3 U = dimgestor::ToUnrealPosition(P[j], S.unit_to_m * 100.0);
		Out[j] = C.RotateVector(FVector(U.x, U.y, U.z));
	}
	return Out;
}

// Percent-encode a token for the query string (RFC 3986 unreserved characters pass through).
FString QueryEscape(const FString& In)
{
	FString Out;
	FTCHARToUTF8 Utf8(*In);
	for (int32 i = 0; i < Utf8.Length(); ++i)
	{
		const uint8 c = uint8(Utf8.Get()[i]);
		if ((c < 128 && FChar::IsAlnum(TCHAR(c))) || c == '-' || c == '_' || c == '.' || c == '~') Out.AppendChar(TCHAR(c));
		else Out += FString::Printf(TEXT("%%%02X"), c);
	}
	return Out;
}

FString Condensed(const TSharedRef<FJsonObject>& Object)
{
	FString Out;
	TSharedRef<TJsonWriter<TCHAR, TCondensedJsonPrintPolicy<TCHAR>>> Writer =
		TJsonWriterFactory<TCHAR, TCondensedJsonPrintPolicy<TCHAR>>::Create(&Out);
	FJsonSerializer::Serialize(Object, Writer);
	return Out;
}
}  // namespace

UDimgestorComponent::UDimgestorComponent()
{
	PrimaryComponentTick.bCanEverTick = true;
	// After animation has run, so our pose is the one rendered.
	PrimaryComponentTick.TickGroup = TG_PostUpdateWork;
	for (const auto& Pair : GMannequinBones) HumanoidToBone.Add(Pair[0], FName(Pair[1]));
}

void UDimgestorComponent::BeginPlay()
{
	Super::BeginPlay();
	if (!TargetMesh && GetOwner()) TargetMesh = GetOwner()->FindComponentByClass<UPoseableMeshComponent>();
	if (!TargetMesh) { LastError = TEXT("no PoseableMeshComponent on the owner: set TargetMesh"); return; }
	for (int32 i = 0; i < TargetMesh->GetNumBones(); ++i)
	{
		const FName Bone = TargetMesh->GetBoneName(i);
		RestPose.Add(Bone, TargetMesh->GetBoneTransformByName(Bone, EBoneSpaces::ComponentSpace));
	}
	FModuleManager::Get().LoadModuleChecked<FWebSocketsModule>(TEXT("WebSockets"));
	Connect();
}

void UDimgestorComponent::EndPlay(const EEndPlayReason::Type Reason)
{
	if (Socket)
	{
		Socket->OnConnected().RemoveAll(this);
		Socket->OnConnectionError().RemoveAll(this);
		Socket->OnClosed().RemoveAll(this);
		Socket->OnMessage().RemoveAll(this);
		Socket->OnBinaryMessage().RemoveAll(this);
		Socket->Close();
		Socket.Reset();
	}
	Super::EndPlay(Reason);
}

void UDimgestorComponent::Connect()
{
	FString FullUrl = Url;
	if (!Token.IsEmpty()) FullUrl += (Url.Contains(TEXT("?")) ? TEXT("&token=") : TEXT("?token=")) + QueryEscape(Token);
	Socket = FWebSocketsModule::Get().CreateWebSocket(FullUrl, TEXT("ws"));
	// WebSocket events arrive on the game thread.
	Socket->OnConnected().AddUObject(this, &UDimgestorComponent::HandleConnected);
	Socket->OnConnectionError().AddUObject(this, &UDimgestorComponent::HandleConnectionError);
	Socket->OnClosed().AddUObject(this, &UDimgestorComponent::HandleClosed);
	Socket->OnMessage().AddUObject(this, &UDimgestorComponent::HandleText);
	Socket->OnBinaryMessage().AddUObject(this, &UDimgestorComponent::HandleBinary);
	ConnectionState = TEXT("connecting");
	Socket->Connect();
}

static constexpr double ResendS = 15, ResumeWithinS = 10;

void UDimgestorComponent::HandleConnected()
{
	if (!ResumeToken.empty() && FPlatformTime::Seconds() - ResumeSince > ResumeWithinS)
	{
		ResumeToken.clear();  // could not resume in time: a fresh session (what was held is dropped)
		LastError = TEXT("could not resume our session after a goaway: a fresh one starts");
	}
	if (!ResumeToken.empty())  // our session goes on here: its audio format, then the token
	{
		ConnectionState = TEXT("resuming");
		SendHello(true);
		SendText(UTF8_TO_TCHAR(dimgestor::ResumeSession(ResumeToken).c_str()));
		return;
	}
	ConnectionState = TEXT("open");
	AudioFormatKey = 0;
	Flow.Reset();
	bAudioPaused = false;
	Sent.clear();
	SentSamples = 0;
	SendHello(false);
}

void UDimgestorComponent::HandleConnectionError(const FString& Error)
{
	// A wrong token shows up here as a failed handshake (HTTP 401).
	LastError = Error;
	ConnectionState = TEXT("closed, retrying");
	ReconnectIn = 2.f;
}

void UDimgestorComponent::HandleClosed(int32 StatusCode, const FString& Reason, bool bWasClean)
{
	if (!ResumeToken.empty())  // after a goaway (1012): on to another worker at once
	{
		ConnectionState = TEXT("moving");
		ReconnectIn = 0.05f;
		return;
	}
	ConnectionState = FString::Printf(TEXT("closed (%d %s), retrying"), StatusCode, *Reason);
	ReconnectIn = 2.f;
}

void UDimgestorComponent::HandleText(const FString& Text)
{
	FTCHARToUTF8 Utf8(*Text);
	dimgestor::Message Message;
	std::string Error;
	if (dimgestor::ParseMessage(std::string(reinterpret_cast<const char*>(Utf8.Get()), Utf8.Length()), Message, Error))
		Handle(Message);
	else LastError = UTF8_TO_TCHAR(Error.c_str());  // one bad message does not end the stream
}

void UDimgestorComponent::HandleBinary(const void* Data, SIZE_T Size, bool bIsLastFragment)
{
	BinaryBuffer.Append(static_cast<const uint8*>(Data), Size);
	if (!bIsLastFragment) return;
	dimgestor::Message Message;
	Message.type = dimgestor::MessageType::Frame;
	std::string Error;
	if (dimgestor::DecodeBinaryFrame(BinaryBuffer.GetData(), BinaryBuffer.Num(), Message.frame, Error,
	                                 bHaveHello ? &Hello : nullptr)) Handle(Message);
	else LastError = UTF8_TO_TCHAR(Error.c_str());
	BinaryBuffer.Reset();
}

void UDimgestorComponent::Handle(const dimgestor::Message& Message)
{
	switch (Message.type)
	{
	case dimgestor::MessageType::Frame:
		Playout.Push(Message.frame, FPlatformTime::Seconds());
		++FramesReceived;
		if (!Message.frame.face.empty()) bFaceWithheld = false;  // the face is back (a later session)
		break;
	case dimgestor::MessageType::Hello:
		Hello = Message.hello;
		bHaveHello = true;
		bNeedBind = true;
		bKeepStream = !ResumeToken.empty();  // a resumed session: its frames and root go on
		if (!bKeepStream) Playout.Reset();
		// Buffer one inference window (the burst length) plus some network jitter.
		Playout.delay_s = (Hello.window_ms > 0 ? Hello.window_ms / 1000.0 : 0.25) + 0.06;
		break;
	case dimgestor::MessageType::Channels:  // the binary frames' layout from the next frame on (e.g. with the face)
		Hello.channels = Message.channels;
		break;
	case dimgestor::MessageType::Status:
		LatencyMs = float(Message.status.latency_ms);
		DroppedFrames = Message.status.dropped;
		break;
	case dimgestor::MessageType::GoAway:
		if (AudioFormatKey != 0 && !Message.resume_token.empty())  // our session moves: hold our audio meanwhile
		{
			ResumeToken = Message.resume_token;
			ResumeSince = FPlatformTime::Seconds();
			++Handovers;
			Flow.SlowDown();
			bAudioPaused = true;
			AudioNotice = TEXT("the server is restarting: moving our session to another worker");
		}
		break;
	case dimgestor::MessageType::SessionResumed:
		if (!ResumeToken.empty())
		{
			ResumeToken.clear();
			++Resumed;
			ConnectionState = TEXT("open");
			bAudioPaused = false;
			AudioNotice = TEXT("our session moved to another worker");
			if (Socket && Socket->IsConnected())
				for (const FSentChunk& C : Sent)  // our audio again from the sample the saved state covers
				{
					if (C.First + C.Samples <= Message.handover_samples) continue;
					const size_t Skip = size_t(std::max<int64>(0, Message.handover_samples - C.First)) * 4 * AudioChannels;
					Socket->Send(C.Bytes.data() + Skip, C.Bytes.size() - Skip, true);
				}
			for (const auto& Chunk : Flow.Resume()) { SendChunks({Chunk}); KeepSent(Chunk); }  // then what was held
			if (Flow.TakeEndPending()) SendAudioEnd();
		}
		break;
	case dimgestor::MessageType::Error:
		if (!ResumeToken.empty() && (Message.error_code == "busy" || Message.error_code == "resume_failed"))
		{
			if (Message.error_code == "busy")  // a worker stopping too: another one (the token stays good)
			{
				if (Socket) Socket->Close();
				break;
			}
			ResumeToken.clear();  // a fresh session from here: what was held starts it
			ConnectionState = TEXT("open");
			bAudioPaused = false;
			for (const auto& Chunk : Flow.Resume()) { SendChunks({Chunk}); KeepSent(Chunk); }
			if (Flow.TakeEndPending()) SendAudioEnd();
		}
		if (Message.error_code == "face_withheld")  // a notice: this session's frames carry no face (at capacity)
		{
			bFaceWithheld = true;
			FaceNotice = UTF8_TO_TCHAR(Message.error_message.c_str());
			break;
		}
		if (Message.error_code == "slow_down")  // a notice, nothing lost: hold our audio until resume
		{
			Flow.SlowDown();
			bAudioPaused = true;
			AudioNotice = TEXT("the server asks us to slow down: holding audio until it resumes");
			break;
		}
		LastError = FString(UTF8_TO_TCHAR(Message.error_code.c_str())) + TEXT(": ") + UTF8_TO_TCHAR(Message.error_message.c_str());
		break;
	case dimgestor::MessageType::Resume:
		bAudioPaused = false;
		AudioNotice = FString::Printf(TEXT("resumed (server backlog %.1f s)"), Message.resume_backlog_s);
		for (const auto& Chunk : Flow.Resume()) { SendChunks({Chunk}); KeepSent(Chunk); }  // what was held, in order
		if (Flow.TakeEndPending()) SendAudioEnd();
		break;
	default:
		break;  // end, pong and unknown types need nothing here
	}
}

void UDimgestorComponent::TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction)
{
	Super::TickComponent(DeltaTime, TickType, ThisTickFunction);
	if (ReconnectIn > 0.f && (ReconnectIn -= DeltaTime) <= 0.f) Connect();
	if (!TargetMesh || !bHaveHello) return;
	if (bNeedBind) Bind();
	if (Playout.Sample(FPlatformTime::Seconds(), Shown))
	{
		Apply(Shown);
		ApplyFace(Shown);
	}
}

float UDimgestorComponent::GetFaceCurve(FName Curve) const
{
	const float* Weight = FaceCurves.Find(Curve);
	return Weight ? *Weight : 0.f;
}

// The face of the frame shown (interpolated with its pose): each name's weight (0..1) as the morph target of
// FaceMesh and the curve in FaceCurves, named through FaceNameMap, else as the face names it (curves in MetaHuman's
// capitalisation).
void UDimgestorComponent::ApplyFace(const dimgestor::Frame& Frame)
{
	if (Frame.face.empty())  // a frame without a face (withheld, or none asked): the face rests, once
	{
		RestFace();
		return;
	}
	bFaceAtRest = false;
	for (const auto& Pair : Frame.face)
	{
		auto It = FaceTargets.find(Pair.first);
		if (It == FaceTargets.end())
		{
			FFaceTarget Target;
			const FName* Mapped = FaceNameMap.Find(FString(UTF8_TO_TCHAR(Pair.first.c_str())));
			std::string Curve = Pair.first;
			if (bMetaHumanCurveNames && !Curve.empty() && Curve[0] >= 'a' && Curve[0] <= 'z') Curve[0] = char(Curve[0] - 'a' + 'A');
			Target.Morph = Mapped ? *Mapped : FName(UTF8_TO_TCHAR(Pair.first.c_str()));
			Target.Curve = Mapped ? *Mapped : FName(UTF8_TO_TCHAR(Curve.c_str()));
			It = FaceTargets.emplace(Pair.first, Target).first;
		}
		const float Weight = float(std::min(1.0, std::max(0.0, Pair.second)));
		FaceCurves.Add(It->second.Curve, Weight);
		if (FaceMesh) FaceMesh->SetMorphTarget(It->second.Morph, Weight);
	}
}

// Every morph target and curve the face drove since it last rested, to 0 (once).
void UDimgestorComponent::RestFace()
{
	if (bFaceAtRest) return;
	for (const auto& Pair : FaceTargets)
	{
		FaceCurves.Add(Pair.second.Curve, 0.f);
		if (FaceMesh) FaceMesh->SetMorphTarget(Pair.second.Morph, 0.f);
	}
	bFaceAtRest = true;
}

void UDimgestorComponent::Bind()
{
	bNeedBind = false;
	Bindings.Reset();
	RestFace();           // the targets the face drove rest before they are forgotten: a frame without a face
	FaceTargets.clear();  // after this would not know them (FaceNameMap may have changed meanwhile)
	SourceRestGlobal = dimgestor::GlobalRotations(Hello.skeleton, Hello.skeleton.rest_rotations);
	auto AddBinding = [this](FName Bone, int32 Joint) {
		const FTransform* Rest = RestPose.Find(Bone);
		if (Rest && Joint >= 0) Bindings.Add(FBinding{Bone, Joint, Rest->GetRotation()});
	};
	if (bMatchJointNames)
	{
		for (int32 j = 0; j < int32(Hello.skeleton.joints.size()); ++j)
			AddBinding(FName(UTF8_TO_TCHAR(Hello.skeleton.joints[j].c_str())), j);
	}
	else
	{
		for (const auto& Pair : Hello.humanoid)
		{
			const FName* Bone = HumanoidToBone.Find(UTF8_TO_TCHAR(Pair.first.c_str()));
			if (Bone) AddBinding(*Bone, Hello.skeleton.IndexOf(Pair.second));
		}
	}
	Bindings.Sort([](const FBinding& A, const FBinding& B) { return A.Joint < B.Joint; });  // parents first
	AlignRests();
	RootBone = NAME_None;
	for (const FBinding& B : Bindings)
		if (Hello.skeleton.parents[B.Joint] < 0) RootBone = B.Bone;
	if (RootBone != NAME_None) RootRestLocation = RestPose[RootBone].GetLocation();
	if (!bKeepStream)
	{
		bHaveRootReference = false;
		LastIndex = -1;
	}
	bKeepStream = false;
	if (Bindings.Num() == 0) LastError = TEXT("no mesh bone matched: check HumanoidToBone / bMatchJointNames");
}

// A per bound bone: the rotation from the mesh's reference bone (bone -> its direction child, component space)
// onto the server skeleton's rest bone between the same joints, so the mesh at rest takes the skeleton's rest
// pose whatever its reference pose (T or A). A bone without a direction child turns with its bound parent.
void UDimgestorComponent::AlignRests()
{
	const dimgestor::Skeleton& S = Hello.skeleton;
	const std::vector<FVector> Source = SourceRestLocations(S, SourceRestGlobal, SourceToComponent.Quaternion());
	std::vector<int32> BindingOf(S.joints.size(), INDEX_NONE);
	for (int32 i = 0; i < Bindings.Num(); ++i) BindingOf[size_t(Bindings[i].Joint)] = i;
	for (FBinding& B : Bindings)  // parents first: a parent's A is known before its children need it
	{
		const int32 Child = DirectionChild(B.Joint, BindingOf);
		if (Child == INDEX_NONE)
		{
			int32 P = S.parents[size_t(B.Joint)];
			while (P >= 0 && BindingOf[size_t(P)] == INDEX_NONE) P = S.parents[size_t(P)];
			B.Align = P >= 0 ? Bindings[BindingOf[size_t(P)]].Align : FQuat::Identity;
			continue;
		}
		const FVector V = RestPose[Bindings[BindingOf[size_t(Child)]].Bone].GetLocation() - RestPose[B.Bone].GetLocation();
		const FVector Src = Source[size_t(Child)] - Source[size_t(B.Joint)];
		const bool bDegenerate = V.SizeSquared() < MinBoneCm * MinBoneCm || Src.SizeSquared() < MinBoneCm * MinBoneCm;
		B.Align = bDegenerate ? FQuat::Identity : FQuat::FindBetweenVectors(V, Src);
	}
}

// The bound joint that says where Joint points (INDEX_NONE: none): the one on the way to its preferred humanoid
// child (the spine for the hips, the neck for the upper chest, the middle finger for a hand), else its first
// bound child.
int32 UDimgestorComponent::DirectionChild(int32 Joint, const std::vector<int32>& BindingOf) const
{
	const dimgestor::Skeleton& S = Hello.skeleton;
	std::map<std::string, std::string> HumanoidOf;  // joint -> humanoid name
	for (const auto& Pair : Hello.humanoid) HumanoidOf[Pair.second] = Pair.first;
	const auto Own = HumanoidOf.find(S.joints[size_t(Joint)]);
	const auto Preferred = Own == HumanoidOf.end() ? GDirectionChildren.end() : GDirectionChildren.find(Own->second);
	if (Preferred != GDirectionChildren.end())
		for (const std::string& Name : Preferred->second)
		{
			const auto It = Hello.humanoid.find(Name);
			int32 j = It == Hello.humanoid.end() ? -1 : S.IndexOf(It->second), Nearest = INDEX_NONE;
			for (; j >= 0 && j != Joint; j = S.parents[size_t(j)])
				if (BindingOf[size_t(j)] != INDEX_NONE) Nearest = j;
			if (j == Joint && Nearest != INDEX_NONE) return Nearest;
		}
	for (const FBinding& B : Bindings)  // by joint index: the first bound child
	{
		int32 P = S.parents[size_t(B.Joint)];
		while (P >= 0 && P != Joint && BindingOf[size_t(P)] == INDEX_NONE) P = S.parents[size_t(P)];
		const auto Name = HumanoidOf.find(S.joints[size_t(B.Joint)]);
		if (P == Joint && (Name == HumanoidOf.end() || !GNotDirections.count(Name->second))) return B.Joint;
	}
	return INDEX_NONE;
}

void UDimgestorComponent::Apply(const dimgestor::Frame& Frame)
{
	const std::vector<dimgestor::Quat> Global = dimgestor::GlobalRotations(Hello.skeleton, Frame.rotations);
	if (Global.empty()) { LastError = TEXT("frame does not match the hello skeleton"); return; }
	const FQuat C = SourceToComponent.Quaternion();
	for (const FBinding& B : Bindings)
	{
		const FQuat Delta = ToFQuat(dimgestor::ToUnrealRotation(Global[B.Joint] * dimgestor::Conjugate(SourceRestGlobal[B.Joint])));
		FTransform T = TargetMesh->GetBoneTransformByName(B.Bone, EBoneSpaces::ComponentSpace);
		T.SetRotation((C * Delta * C.Inverse() * B.Align * B.RestComponent).GetNormalized());
		TargetMesh->SetBoneTransformByName(B.Bone, T, EBoneSpaces::ComponentSpace);
	}
	if (Frame.index < LastIndex) bHaveRootReference = false;  // a new stream (own audio session, --loop)
	LastIndex = Frame.index;
	if (bApplyRootPosition && RootBone != NAME_None)
	{
		const double UnitToCm = Hello.skeleton.unit_to_m * 100.0;
		if (!bHaveRootReference)
		{
			RootReference = Frame.root;
			const double SourceHeight = dimgestor::ToUnrealPosition(Frame.root, UnitToCm).z;
			RootScale = SourceHeight > 10.0 && RootRestLocation.Z > 10.0 ? float(RootRestLocation.Z / SourceHeight) : 1.f;
			bHaveRootReference = true;
		}
		const dimgestor::Vec3 Rel{Frame.root.x - RootReference.x, Frame.root.y - RootReference.y, Frame.root.z - RootReference.z};
		const dimgestor::Vec3 D = dimgestor::ToUnrealPosition(Rel, UnitToCm);
		FTransform T = TargetMesh->GetBoneTransformByName(RootBone, EBoneSpaces::ComponentSpace);
		T.SetLocation(RootRestLocation + C.RotateVector(FVector(D.x, D.y, D.z)) * RootScale);
		TargetMesh->SetBoneTransformByName(RootBone, T, EBoneSpaces::ComponentSpace);
	}
}

// Our hello: the frames' encoding, the face's name set (revision 7: the server then lays the face out in binary
// frames and says so with a `channels` message), the speaker (revision 9) and, once we send audio, its format.
void UDimgestorComponent::SendHello(bool bWithAudio)
{
	TSharedRef<FJsonObject> ClientHello = MakeShared<FJsonObject>();
	ClientHello->SetStringField(TEXT("type"), TEXT("hello"));
	ClientHello->SetNumberField(TEXT("protocol"), dimgestor::kProtocolVersion);
	ClientHello->SetStringField(TEXT("encoding"), bBinaryFrames ? TEXT("binary") : TEXT("json"));
	if (!FaceNames.IsEmpty()) ClientHello->SetStringField(TEXT("face"), FaceNames);
	if (!Speaker.IsEmpty()) ClientHello->SetStringField(TEXT("speaker"), Speaker);  // (revision 9)
	if (bWithAudio)
	{
		TSharedRef<FJsonObject> Audio = MakeShared<FJsonObject>();
		Audio->SetNumberField(TEXT("rate"), AudioRate);
		Audio->SetStringField(TEXT("format"), TEXT("float32"));
		Audio->SetNumberField(TEXT("channels"), AudioChannels);
		ClientHello->SetObjectField(TEXT("audio"), Audio);
		AudioFormatKey = AudioRate * 16 + AudioChannels;
	}
	SendText(Condensed(ClientHello));
}

void UDimgestorComponent::KeepSent(const dimgestor::AudioFlow::Chunk& Chunk)
{
	const int64 N = int64(Chunk.size() / (4 * size_t(AudioChannels)));
	Sent.push_back(FSentChunk{SentSamples, Chunk, N});
	SentSamples += N;
	while (Sent.size() > 1 && double(SentSamples - Sent.front().First - Sent.front().Samples) > ResendS * AudioRate)
		Sent.erase(Sent.begin());
}

bool UDimgestorComponent::SendAudio(const TArray<float>& Samples, int32 SampleRate, int32 Channels)
{
	const bool bMoving = !ResumeToken.empty();  // our session is moving to another worker: held meanwhile
	if (!bMoving && (!Socket || !Socket->IsConnected())) return false;
	if (!bMoving && SampleRate * 16 + Channels != AudioFormatKey)  // declare the format before the first chunk
	{
		Flow.DropHeld();  // (held audio of another format cannot follow the new hello)
		AudioRate = SampleRate;
		AudioChannels = Channels;
		Sent.clear();
		SentSamples = 0;
		SendHello(true);
	}
	// float32 little-endian on the wire; every platform Unreal ships on is little-endian.
	const uint8* Bytes = reinterpret_cast<const uint8*>(Samples.GetData());
	Flow.max_held_s = MaxHeldAudioS;
	const bool bWasDropping = Flow.dropped_chunks() > 0;
	for (const auto& Chunk : Flow.Offer(dimgestor::AudioFlow::Chunk(Bytes, Bytes + Samples.Num() * sizeof(float)),
	                                    double(Samples.Num()) / (double(Channels) * SampleRate)))
	{
		SendChunks({Chunk});
		KeepSent(Chunk);
	}
	DroppedAudioS = float(Flow.dropped_s());
	if (!bWasDropping && Flow.dropped_chunks() > 0)
		AudioNotice = FString::Printf(TEXT("paused by the server for over %.0f s: dropping the oldest audio (DroppedAudioS)"), MaxHeldAudioS);
	return true;
}

void UDimgestorComponent::EndAudio()
{
	if (Flow.End()) SendAudioEnd();  // paused: at resume, after the held audio
}

void UDimgestorComponent::SendAudioEnd()
{
	TSharedRef<FJsonObject> End = MakeShared<FJsonObject>();
	End->SetStringField(TEXT("type"), TEXT("audio_end"));
	SendText(Condensed(End));
}

void UDimgestorComponent::SendChunks(const std::vector<dimgestor::AudioFlow::Chunk>& Chunks)
{
	if (!Socket || !Socket->IsConnected()) return;
	for (const auto& Chunk : Chunks) Socket->Send(Chunk.data(), Chunk.size(), true);
}

void UDimgestorComponent::SendText(const FString& Text)
{
	if (Socket && Socket->IsConnected()) Socket->Send(Text);
}
