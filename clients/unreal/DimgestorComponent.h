// Unreal client for dimgestor (protocol v1 revision 7): receives gesture frames over a WebSocket (WebSockets module)
// and poses a UPoseableMeshComponent by bone name; the face sets morph targets of a skeletal mesh and/or curves by
// name for an Animation Blueprint (MetaHuman). Decoding is in the engine-independent DimgestorProtocol.
#pragma once

#include "CoreMinimal.h"
#include "Components/ActorComponent.h"
#include "DimgestorAudioFlow.h"
#include "DimgestorPlayout.h"
#include "DimgestorProtocol.h"
#include "DimgestorComponent.generated.h"

class IWebSocket;
class UPoseableMeshComponent;
class USkeletalMeshComponent;

UCLASS(ClassGroup = (Animation), meta = (BlueprintSpawnableComponent))
class UDimgestorComponent : public UActorComponent
{
	GENERATED_BODY()

public:
	UDimgestorComponent();

	/** Server WebSocket URL (streamer serve --ws HOST:PORT). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	FString Url = TEXT("ws://127.0.0.1:8765/");

	/** Access token when the server runs with --token (sent as ?token=). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	FString Token;

	/** Receive DGF1 binary frames (smaller, faster to decode) instead of JSON. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	bool bBinaryFrames = true;

	/** Mesh to pose; when empty, the first PoseableMeshComponent on the owner. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	TObjectPtr<UPoseableMeshComponent> TargetMesh;

	/** Unity HumanBodyBones name (as in the server's "humanoid" map) -> bone of your mesh.
	 *  Defaults to the UE5 Mannequin (pelvis, spine_01, upperarm_l, ...). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	TMap<FString, FName> HumanoidToBone;

	/** Ignore HumanoidToBone and drive every mesh bone named like a server skeleton joint
	 *  (for a mesh imported from the training skeleton's BVH/FBX). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	bool bMatchJointNames = false;

	/** Rotation from the server's forward (+X after conversion) to the mesh's component space.
	 *  UE Mannequin and MetaHuman meshes face +Y: yaw 90. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	FRotator SourceToComponent = FRotator(0.f, 90.f, 0.f);

	/** Move the root bone with the source root (scaled to the mesh's hip height). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	bool bApplyRootPosition = true;

	/** Face name set to ask the server for: arkit (52 ARKit names: MetaHuman, Live Link Face, Ready Player Me),
	 *  vrm0, vrm1, oculus (visemes); none: no face. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor|Face")
	FString FaceNames = TEXT("arkit");

	/** A speaker of a model trained on several (the server's hello lists them in `speakers`): our sessions play
	 *  that speaker's style; empty: the server's default. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	FString Speaker;

	/** Skeletal mesh whose morph targets the face sets (SetMorphTarget by name); empty: curves only. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor|Face")
	TObjectPtr<USkeletalMeshComponent> FaceMesh = nullptr;

	/** Face name -> your morph target / curve name, where they differ (e.g. jawOpen -> Mouth_Open). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor|Face")
	TMap<FString, FName> FaceNameMap;

	/** Curves named as MetaHuman's ARKit mapping and Live Link Face name them (jawOpen -> JawOpen); morph targets
	 *  keep the face name. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor|Face")
	bool bMetaHumanCurveNames = true;

	/** The face shown now (interpolated with the pose), curve name -> weight 0..1: feed it to a Modify Curve node
	 *  (its Curve Map pin) in your face's Animation Blueprint. */
	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Face")
	TMap<FName, float> FaceCurves;

	/** One curve of FaceCurves (0 when the face has no such name). */
	UFUNCTION(BlueprintPure, Category = "Dimgestor|Face")
	float GetFaceCurve(FName Curve) const;

	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	FString ConnectionState = TEXT("idle");

	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	int64 FramesReceived = 0;

	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	float LatencyMs = 0.f;

	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	int64 DroppedFrames = 0;

	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	FString LastError;

	/** Audio held while the server has us paused (slow_down until resume); beyond it the oldest is dropped. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Dimgestor")
	float MaxHeldAudioS = float(dimgestor::kDefaultMaxHeldS);

	/** Between the server's slow_down and its resume (protocol revision 2): SendAudio holds the audio. */
	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	bool bAudioPaused = false;

	/** Seconds of audio held beyond MaxHeldAudioS while paused, and so dropped (oldest first). */
	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	float DroppedAudioS = 0.f;

	/** Hand-overs (protocol revision 3): goaways while we had our own session, and sessions resumed elsewhere. */
	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	int32 Handovers = 0;
	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	int32 Resumed = 0;

	/** What flow control is doing (paused, resumed, dropping); not an error. */
	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Status")
	FString AudioNotice;

	/** The server admitted this session without the face it asked (`face_withheld`: the worker is at capacity for
	 *  faces, `serve --faces-beyond-capacity no-face`): the body goes on and the face rests at 0. Cleared when a frame
	 *  with a face comes (the server asks again at the next session). Not an error: FaceNotice says why. */
	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Face")
	bool bFaceWithheld = false;
	UPROPERTY(VisibleAnywhere, BlueprintReadOnly, Category = "Dimgestor|Face")
	FString FaceNotice;

	/** Send your own audio (mono or interleaved float samples) for an own session; declares the format first.
	 *  Held (at most MaxHeldAudioS) while the server has us paused, and sent in order at its resume. */
	UFUNCTION(BlueprintCallable, Category = "Dimgestor")
	bool SendAudio(const TArray<float>& Samples, int32 SampleRate, int32 Channels = 1);

	/** No more audio: the server finishes the session and sends "end" (if paused: at resume, after the held audio). */
	UFUNCTION(BlueprintCallable, Category = "Dimgestor")
	void EndAudio();

	virtual void BeginPlay() override;
	virtual void EndPlay(const EEndPlayReason::Type Reason) override;
	virtual void TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction) override;

private:
	struct FBinding
	{
		FName Bone;
		int32 Joint = INDEX_NONE;
		FQuat RestComponent;  // the bone's component-space rotation in the mesh's rest pose
		FQuat Align = FQuat::Identity;  // A: turns the mesh's rest bone onto the server skeleton's rest bone
	};

	void Connect();
	void HandleConnected();
	void HandleConnectionError(const FString& Error);
	void HandleClosed(int32 StatusCode, const FString& Reason, bool bWasClean);
	void HandleText(const FString& Text);
	void HandleBinary(const void* Data, SIZE_T Size, bool bIsLastFragment);
	void Handle(const dimgestor::Message& Message);
	void Bind();
	void AlignRests();
	int32 DirectionChild(int32 Joint, const std::vector<int32>& BindingOf) const;
	void Apply(const dimgestor::Frame& Frame);
	void ApplyFace(const dimgestor::Frame& Frame);
	void RestFace();
	void SendHello(bool bWithAudio);
	void SendText(const FString& Text);
	void SendChunks(const std::vector<dimgestor::AudioFlow::Chunk>& Chunks);
	void SendAudioEnd();
	void KeepSent(const dimgestor::AudioFlow::Chunk& Chunk);

	TSharedPtr<IWebSocket> Socket;
	TArray<uint8> BinaryBuffer;  // fragments of the binary message being received
	float ReconnectIn = 0.f;
	int32 AudioFormatKey = 0;    // SampleRate * 16 + Channels declared in our last hello
	dimgestor::AudioFlow Flow;   // slow_down / resume (protocol revision 2); all on the game thread
	// Hand-over (revision 3): after a goaway our audio is held and the last ResendS seconds we sent are kept, to
	// be sent again from the sample the saved state covers once the session is resumed on another worker.
	struct FSentChunk { int64 First; dimgestor::AudioFlow::Chunk Bytes; int64 Samples; };
	std::vector<FSentChunk> Sent;
	int64 SentSamples = 0;
	int32 AudioRate = 0, AudioChannels = 1;
	std::string ResumeToken;     // from a goaway until session_resumed
	double ResumeSince = 0;      // FPlatformTime::Seconds() of the goaway
	bool bKeepStream = false;    // the next hello is the resumed session's: its frames and root go on

	bool bHaveHello = false;
	bool bNeedBind = false;
	dimgestor::Hello Hello;
	dimgestor::FramePlayout Playout;  // frames come in bursts: each is shown at its presentation time
	dimgestor::Frame Shown;
	std::vector<dimgestor::Quat> SourceRestGlobal;
	TArray<FBinding> Bindings;
	TMap<FName, FTransform> RestPose;  // component-space bone transforms captured at BeginPlay
	FName RootBone;
	FVector RootRestLocation = FVector::ZeroVector;
	bool bHaveRootReference = false;
	dimgestor::Vec3 RootReference;
	float RootScale = 1.f;
	int64 LastIndex = -1;
	struct FFaceTarget { FName Morph, Curve; };
	std::map<std::string, FFaceTarget> FaceTargets;
	bool bFaceAtRest = true;  // every face target set to 0 since the last frame with a face  // face name -> its names here (worked out once per hello)
};
