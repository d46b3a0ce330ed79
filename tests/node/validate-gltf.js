// Validate one glTF 2.0 asset (.glb, .gltf, or a glTF-based file such as .vrm / .vrma) with the Khronos glTF
// validator (npm gltf-validator), reading external buffers and images beside it.
//
// Usage: node validate-gltf.js FILE
// Output (stdout): the validator's JSON report, every issue listed (maxIssues 0).
// Exit status 0 when the report has no errors, 1 when it has, 2 when the validator could not read the file.
"use strict";
const fs = require("fs");
const path = require("path");
const validator = require("gltf-validator");

const file = path.resolve(process.argv[2]);
validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {
  uri: path.basename(file),
  maxIssues: 0,
  externalResourceFunction: (uri) =>
    fs.promises.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri))).then((b) => new Uint8Array(b)),
}).then(
  (report) => {
    process.stdout.write(JSON.stringify(report));
    process.exitCode = report.issues.numErrors > 0 ? 1 : 0;
  },
  (err) => {  // not glTF at all (no GLB magic, no JSON), or bad arguments
    process.stderr.write(`gltf-validator could not read ${file}: ${err}\n`);
    process.exitCode = 2;
  },
);
