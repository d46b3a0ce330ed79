"""Run inside Blender (tests/helpers/blender.py starts it): import one .glb/.gltf or .bvh, step through each key of
its animation and write every armature bone's evaluated head in world space, in Blender's own Z-up coordinates.

Usage: blender -b --factory-startup --python bone_positions.py -- FILE OUT.json
OUT.json: {"names": [bone, ...], "frames": [...], "times": [s, ...], "positions": [[[x, y, z] per bone] per key]}.
Exit status 3 when a glTF file needs numpy and Blender's Python has none."""

import builtins
import json
import sys

import bpy
from io_anim_bvh import import_bvh

try:
    import numpy
except ImportError:
    numpy = None

# Debian's Blender 3.4 runs its add-ons on newer Python and numpy than they were written for: the BVH reader opens
# files in mode 'rU' (gone in Python 3.11) and the glTF importer uses np.bool (gone in numpy 1.24).
import_bvh.open = lambda path, mode="r", *a, **kw: builtins.open(path, mode.replace("U", ""), *a, **kw)
if numpy is not None and "bool" not in numpy.__dict__:
    numpy.bool = bool

src, out = sys.argv[sys.argv.index("--") + 1:]
scene = bpy.context.scene
if src.lower().endswith(".bvh"):
    # File frame k (from 0) becomes frame 1 + k, and the scene's rate the file's (fps / fps_base = 1 / Frame Time);
    # the armature object carries the Y-up -> Z-up turn.
    bpy.ops.import_anim.bvh(filepath=src, axis_forward="-Z", axis_up="Y", global_scale=1.0, frame_start=1,
                            use_fps_scale=False, update_scene_fps=True, rotate_mode="NATIVE")
    start, seconds_per_frame = 1, scene.render.fps_base / scene.render.fps
else:
    if numpy is None:
        print("Blender's Python has no numpy: its glTF importer needs it", file=sys.stderr)
        sys.exit(3)
    # The importer keys a sampler's time t at frame t * render.fps (fps_base ignored), from frame 0.
    bpy.ops.import_scene.gltf(filepath=src)
    start, seconds_per_frame = 0, 1.0 / scene.render.fps

armatures = [o for o in scene.objects if o.type == "ARMATURE"]
keys = sorted({round(k.co.x, 4) for o in armatures if o.animation_data and o.animation_data.action
               for c in o.animation_data.action.fcurves for k in c.keyframe_points})
if not keys:  # no animation: the rest pose alone
    keys = [float(start)]
names = [b.name for o in armatures for b in o.pose.bones]
positions = []
for f in keys:
    scene.frame_set(int(f // 1), subframe=f % 1)  # between two frames when a key is not on one
    depsgraph = bpy.context.evaluated_depsgraph_get()
    row = []
    for o in armatures:
        e = o.evaluated_get(depsgraph)
        row += [list(e.matrix_world @ b.head) for b in e.pose.bones]
    positions.append(row)
with open(out, "w") as f:
    json.dump({"names": names, "frames": keys, "times": [(k - start) * seconds_per_frame for k in keys],
               "positions": positions}, f)
