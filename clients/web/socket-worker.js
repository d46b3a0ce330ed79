// The viewer's WebSocket, in a Web Worker (issue 24): the page's main thread draws the avatar, and on a slow
// (software-rendered) page every message through it waits for a drawing to finish. Here the microphone's chunks
// come straight from the AudioWorklet (a MessagePort, no main-thread hop) and are sent at once; frames are parsed
// and stamped on arrival here, on the page's clock (performance.timeOrigin relates the two), and the page reads
// them when it draws. Microphone flow control (audio-flow.js) and the hand-over's re-send live here too, so the
// audio's order never depends on the main thread: slow_down, goaway and resume are acted on as they arrive.
//
// Frames down go into a ring in shared memory when the page is cross-origin isolated (the server sends the headers):
// the page reads the ring at each draw, so a frame that came while it was drawing is shown at the very next draw,
// not after the messages queued behind that draw. The ring comes with the hello; without isolation frames are
// posted like every other message.
//
// Page -> worker: init {pageOrigin} | connect {id, url, hello, resume} | close {code, reason} | send {text} |
//                 ping | mic {port, rate, format} | micStop | audioEnd
// Worker -> page: open {id} | close {id, code, reason} | message {id, msg, at} | frame {id, frame, at} |
//                 ring {id, ring, layout} | sourceAudio {id, chunk, at} | bad {id, message} |
//                 mic {said, sent, dropped, flow, ...}
//                 (a hello or `channels` message, and `ring`, carry `ring`, the SharedArrayBuffer the frames go to
//                 from then on, and its `layout` {joints, channels, faceLabels}: frame-ring.js)
//
// The face (revision 7): a JSON frame's `face` is passed on as it is; a binary frame's comes in the channel layout
// the server's `channels` message announced after our hello asked for a face (protocol.js decodes it into `face`
// too). A ring holds one layout: a `channels` message, or frames whose face has other names, get a new one.
// (`at`: arrival, ms on the page's performance.now clock)
import { AudioFlow } from './audio-flow.js';
import { FrameRing } from './frame-ring.js';
import { binaryKind, decodeBinaryFrame, decodeSourceAudio } from './protocol.js';

const MAX_SEND_BUFFER = 1 << 20;  // bytes queued in the socket before mic chunks are dropped
const RESEND_S = 15;  // our audio kept after it is sent: a hand-over re-sends it from the sample the state covers

let originShift = 0;  // page clock = worker clock + this (ms)
const pageNow = () => performance.now() + originShift;

let ws = null;
let id = null;         // the page's id of the current connection: events carry it, so stale ones are ignored
let talk = false;      // this connection declared audio in its hello
let moving = false;    // a goaway came while talking: audio is held until session_resumed (or a fresh session)
let mic = null;        // {port, rate, format, samples} while the microphone feeds us
let flow = null;       // AudioFlow of this talk (outlives the microphone: what is held goes at `resume`)
let ring = null;       // FrameRing of this connection's stream (from its hello on) when memory can be shared
let serverHello = null;  // this connection's hello from the server: the binary frame layout (joints, channels)
let layout = null;       // the channels binary frames carry now: the hello's, then each `channels` message's
let endPending = false;  // audio_end waits for the held audio
const sent = { chunks: [], samples: 0 };  // [first sample, buffer, samples] of our recent audio; samples sent
const counts = { sent: 0, dropped: 0 };

const post = (m, transfer = []) => self.postMessage(m, transfer);
const isOpen = () => ws !== null && ws.readyState === WebSocket.OPEN;

self.onmessage = (e) => {
  const m = e.data;
  switch (m.type) {
    case 'init': originShift = performance.timeOrigin - m.pageOrigin; break;
    case 'connect': connect(m); break;
    case 'close': closeSocket(m.code, m.reason); break;
    case 'send': if (isOpen()) ws.send(m.text); break;
    case 'ping': if (isOpen()) ws.send(JSON.stringify({ type: 'ping', t: pageNow() })); break;
    case 'mic': startMic(m); break;
    case 'micStop': stopMic(); break;
    case 'audioEnd':
      if (flow && flow.paused) endPending = true;  // after the held audio, at `resume`
      else if (isOpen()) ws.send(JSON.stringify({ type: 'audio_end' }));
      report();
      break;
    default: post({ type: 'bad', id, message: `socket worker: unknown command ${JSON.stringify(m.type)}` });
  }
};

function closeSocket(code = 1000, reason = '') {
  if (!ws) return;
  const old = ws;
  ws = null;
  old.close(code, reason);
}

function connect({ id: newId, url, hello, resume }) {
  closeSocket(1000, 'reconnect');
  id = newId;
  ring = null;
  serverHello = null;
  layout = null;
  talk = !!hello.audio;
  endPending = false;
  if (!resume) {  // a fresh session: what was sent or held belongs to the old one
    moving = false;
    sent.chunks.length = 0;
    sent.samples = 0;
    if (flow) { flow.take(); flow.paused = false; }
  }
  const sock = new WebSocket(url);
  sock.binaryType = 'arraybuffer';
  ws = sock;
  const myId = newId;
  sock.onopen = () => {
    if (sock !== ws) return;
    sock.send(JSON.stringify(hello));
    if (resume) sock.send(JSON.stringify({ type: 'resume_session', token: resume }));
    post({ type: 'open', id: myId });
  };
  sock.onmessage = (ev) => { if (sock === ws) receive(ev.data, myId); };
  sock.onclose = (ev) => {
    if (sock !== ws) return;  // a socket replaced on purpose
    ws = null;
    post({ type: 'close', id: myId, code: ev.code, reason: ev.reason });
  };
}

function receive(data, myId) {
  const at = pageNow();
  if (typeof data !== 'string') {
    try {
      if (binaryKind(data) === 'DGA1') {
        const chunk = decodeSourceAudio(data);
        post({ type: 'sourceAudio', id: myId, chunk, at }, [chunk.samples.buffer]);
      } else sendFrame(decodeBinaryFrame(data, serverHello, layout), true, at, myId);
    } catch (e) { post({ type: 'bad', id: myId, message: e.message }); }
    return;
  }
  let msg;
  try { msg = JSON.parse(data); } catch (e) {
    post({ type: 'bad', id: myId, message: `unparsable message: ${data.slice(0, 80)}` });
    return;
  }
  if (msg.type === 'frame') { sendFrame(msg, false, at, myId); return; }
  if (msg.type === 'hello') {
    serverHello = msg;
    layout = Array.isArray(msg.channels) ? msg.channels : [];
    ring = null;
  }
  if (msg.type === 'channels' && Array.isArray(msg.channels)) layout = msg.channels;
  if (talk && flow) audioControl(msg);  // before the page hears of it: the page's view of the flow is then current
  if ((msg.type === 'hello' || (msg.type === 'channels' && ring)) && self.crossOriginIsolated && serverHello &&
      serverHello.skeleton && Array.isArray(serverHello.skeleton.joints)) {
    const face = layout.find((c) => c.name === 'face');
    const labels = face && Array.isArray(face.labels) ? face.labels : (ring ? ring.faceLabels : []);
    post({ type: 'message', id: myId, msg, at, ...newRing(labels) });
    return;
  }
  post({ type: 'message', id: myId, msg, at });
}

/** A fresh ring for the current layout and a face of `faceLabels`: {ring, layout} for the page. */
function newRing(faceLabels) {
  ring = FrameRing.create(serverHello.skeleton.joints.length, layout, faceLabels);
  return { ring: ring.sab, layout: { joints: ring.joints, channels: layout, faceLabels: ring.faceLabels } };
}

function sendFrame(frame, binary, at, myId) {
  if (ring && !ring.fitsFace(frame)) post({ type: 'ring', id: myId, ...newRing(Object.keys(frame.face)) });
  if (!(ring && ring.write(frame, binary, at))) post({ type: 'frame', id: myId, frame, binary, at });
}

/** The server's flow control and hand-over, acted on here so no chunk is sent out of turn. */
function audioControl(msg) {
  if (msg.type === 'error' && msg.code === 'slow_down') flow.slowDown();
  else if (msg.type === 'goaway' && msg.resume_token) { moving = true; flow.slowDown(); }
  else if (msg.type === 'resume') { for (const b of flow.resume()) sendNow(b); if (endPending) sendEnd(); }
  else if (msg.type === 'session_resumed' && moving) { moving = false; resendFrom(msg.samples); }
  else return;
  report();
}

function sendEnd() {
  endPending = false;
  ws.send(JSON.stringify({ type: 'audio_end' }));
}

function startMic({ port, rate, format }) {
  stopMic();
  mic = { port, rate, format, samples: 0 };
  flow = new AudioFlow(rate);
  counts.sent = 0;
  counts.dropped = 0;
  port.onmessage = (e) => onChunk(e.data);
}

function stopMic() {
  if (!mic) return;
  mic.port.onmessage = null;
  mic.port.close();
  mic = null;
}

function onChunk(f32) {
  if (!mic || !talk) return;
  if (!moving && !isOpen()) return;  // (moving: held below, sent at session_resumed)
  if (!flow.paused && ws.bufferedAmount > MAX_SEND_BUFFER) { counts.dropped++; report(); return; }  // bounded
  const buf = encode(f32, mic.format);
  // Our own speech: this chunk's last sample was said just now, at pts = the samples the server gets up to it.
  mic.samples += f32.length;
  const said = [(mic.samples - flow.droppedSamples) / mic.rate, pageNow() / 1000];
  const dropped = flow.droppedChunks;
  for (const b of flow.offer(buf, f32.length)) sendNow(b);  // paused (slow_down, goaway): held, bounded
  counts.dropped += flow.droppedChunks - dropped;
  report(said, flow.droppedChunks > dropped && dropped === 0);
}

function encode(f32, format) {
  let buf;
  if (format === 'float32') {
    buf = new ArrayBuffer(f32.length * 4);
    const dv = new DataView(buf);
    for (let i = 0; i < f32.length; i++) dv.setFloat32(i * 4, f32[i], true);
  } else {
    buf = new ArrayBuffer(f32.length * 2);
    const dv = new DataView(buf);
    for (let i = 0; i < f32.length; i++) dv.setInt16(i * 2, Math.round(Math.max(-1, Math.min(1, f32[i])) * 32767), true);
  }
  return buf;
}

const bytesPerSample = () => (mic && mic.format === 'float32' ? 4 : 2);

function sendNow(buf) {
  if (!isOpen()) return;
  ws.send(buf);
  counts.sent++;
  const n = buf.byteLength / bytesPerSample();
  sent.chunks.push([sent.samples, buf, n]);
  sent.samples += n;
  const keep = RESEND_S * (mic ? mic.rate : 48000);
  while (sent.chunks.length > 1 && sent.samples - sent.chunks[0][0] - sent.chunks[0][2] > keep) sent.chunks.shift();
}

function resendFrom(sample) {
  // The audio after `sample` again, in order (the chunk that straddles it cut), then what was held meanwhile.
  const bytes = bytesPerSample();
  for (const [first, buf, n] of sent.chunks) {
    if (first + n <= sample) continue;
    const skip = Math.max(0, sample - first);
    ws.send(skip ? buf.slice(skip * bytes) : buf);
    counts.sent++;
  }
  for (const b of flow.resume()) sendNow(b);
  if (endPending) sendEnd();
}

/** The microphone's counts and flow state to the page (HUD, tests); `said` dates the chunk just taken. */
function report(said = null, startedDropping = false) {
  if (!flow) return;
  post({ type: 'mic', said, startedDropping, sent: counts.sent, dropped: counts.dropped, endPending,
         flow: { paused: flow.paused, pauses: flow.pauses, resumes: flow.resumes, heldS: flow.heldS,
                 droppedS: flow.droppedS, droppedChunks: flow.droppedChunks, droppedSamples: flow.droppedSamples } });
}
