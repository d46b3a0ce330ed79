// Test driver: PoseDecoder (../pose-decoder.js) and the One Euro filter (../frame-step-stream.js) on given rows.
// usage: node pose_decoder_check.mjs INPUT.json
//   INPUT: {spec: {mean, std, joints, numJoints, heading, fps}, root, tether_s, rows: [[D normalized floats]...],
//           filter: {fps, hz, beta}}
// Prints one JSON object: {features, root, rotations} per row decoded in order, and `filtered`: the rows through
// the filter in two calls (split after the first third); tests/test_clients_web_local.py compares with Python.
import { readFileSync } from 'node:fs';
import { PoseDecoder } from '../pose-decoder.js';
import { OneEuroFilter } from '../frame-step-stream.js';

const input = JSON.parse(readFileSync(process.argv[2], 'utf8'));
const decoder = new PoseDecoder(input.spec, input.root, input.tether_s);
const poses = input.rows.map((r) => decoder.decode(Float32Array.from(r)));
const f = new OneEuroFilter(input.filter.fps, input.filter.hz, input.filter.beta);
const cut = Math.floor(input.rows.length / 3);
const filtered = [...f.step(input.rows.slice(0, cut)), ...f.step(input.rows.slice(cut))].map((r) => Array.from(r));
console.log(JSON.stringify({ features: poses.map((p) => p.features), root: poses.map((p) => p.root),
                             rotations: poses.map((p) => p.rotations), filtered }));
