// Parse captured VMC datagrams with the npm `osc` package (an OSC implementation independent of ours)
// and apply EVMC4U's per-address argument-type checks (ExternalReceiver.ProcessMessage): a message whose
// types do not match is silently ignored there, so here it is an error.
//
// Input: a file of datagrams, each prefixed by its length (uint32 big-endian).
// Output (stdout): JSON {datagrams, bundles, messages: {address: count}, frames: [[T, bones, ...]], errors: [...]}.
// Exit status 1 when any datagram fails to parse or any message breaks the expected types.
"use strict";
const fs = require("fs");
const osc = require("osc");

// address -> the OSC type tags EVMC4U requires of the leading arguments (s string, f float32, i int32)
const EXPECTED = {
  "/VMC/Ext/Root/Pos": "sfffffff",
  "/VMC/Ext/Bone/Pos": "sfffffff",
  "/VMC/Ext/Blend/Val": "sf",
  "/VMC/Ext/Blend/Apply": "",
  "/VMC/Ext/OK": "i",
  "/VMC/Ext/T": "f",
};

const data = fs.readFileSync(process.argv[2]);
const out = { datagrams: 0, bundles: 0, messages: {}, frames: [], errors: [] };
let bones = 0;

function visit(packet, where) {
  if (packet.packets !== undefined) {  // a bundle
    out.bundles += 1;
    packet.packets.forEach((p, i) => visit(p, `${where}[${i}]`));
    return;
  }
  const want = EXPECTED[packet.address];
  if (want === undefined) {
    out.errors.push(`${where}: unexpected address ${packet.address}`);
    return;
  }
  const got = packet.args.map((a) => a.type).join("");
  if (got !== want) out.errors.push(`${where}: ${packet.address} has types ${got || "(none)"}, EVMC4U needs ${want || "(none)"}`);
  packet.args.forEach((a, i) => {
    if (a.type === "f" && !Number.isFinite(a.value)) out.errors.push(`${where}: ${packet.address} argument ${i} is ${a.value}`);
  });
  out.messages[packet.address] = (out.messages[packet.address] || 0) + 1;
  if (packet.address === "/VMC/Ext/Bone/Pos") bones += 1;
  if (packet.address === "/VMC/Ext/T") {
    out.frames.push([packet.args[0].value, bones]);
    bones = 0;
  }
}

let at = 0;
while (at + 4 <= data.length) {
  const n = data.readUInt32BE(at);
  const dgram = data.subarray(at + 4, at + 4 + n);
  at += 4 + n;
  out.datagrams += 1;
  try {
    visit(osc.readPacket(new Uint8Array(dgram), { metadata: true }), `datagram ${out.datagrams - 1}`);
  } catch (e) {
    out.errors.push(`datagram ${out.datagrams - 1}: osc.readPacket failed: ${e.message}`);
  }
}
if (at !== data.length) out.errors.push(`trailing ${data.length - at} bytes`);
process.stdout.write(JSON.stringify(out));
process.exit(out.errors.length ? 1 : 0);
