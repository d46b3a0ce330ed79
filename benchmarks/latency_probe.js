// Injected by benchmarks/latency.py before the web viewer loads (Page.addScriptToEvaluateOnNewDocument): stamps,
// on the page's performance.now(), every step of the Talk path that the page sees, without changing the viewer:
//   sends   each audio message sent: [time, samples, when its microphone chunk reached the page, the chunk's first
//           sample above ONSET or -1, the chunk's peak |x|]
//   texts   `timing` and `pong` messages (arrival, JSON); the viewer's hello asks for `timing`
//   arrive  each frame the playout clock is told of (pts, arrival)
//   shown   each requestAnimationFrame's presented time (rAF time, pts presented by the playout clock)
(() => {
  const L = window.__latency = { mic: [], sends: [], texts: [], arrive: [], shown: [], ws: null, format: null,
                                 pending: null, inRaf: false };
  const ONSET = 0.05;  // an onset: the first sample above this after quiet chunks (latency.py says how quiet)

  const Node = window.AudioWorkletNode;
  if (Node) {
    window.AudioWorkletNode = class extends Node {
      constructor(ctx, name, options) {
        super(ctx, name, options);
        this.port.addEventListener('message', (e) => {  // runs before the viewer's onmessage (registered later)
          const x = e.data;
          let first = -1, peak = 0;  // the first sample above ONSET, and the chunk's peak
          for (let i = 0; i < x.length; i++) {
            const a = Math.abs(x[i]);
            if (a > ONSET && first < 0) first = i;
            peak = Math.max(peak, a);
          }
          L.pending = { at: performance.now(), samples: x.length, first, peak };
        });
      }
    };
  }

  const Socket = window.WebSocket;
  window.WebSocket = class extends Socket {
    constructor(...args) {
      super(...args);
      L.ws = this;
      this.addEventListener('message', (e) => {
        if (typeof e.data === 'string' && (e.data.includes('"timing"') || e.data.includes('"pong"')))
          L.texts.push([performance.now(), e.data]);
      });
    }
    send(data) {
      if (typeof data === 'string') {
        const msg = JSON.parse(data);
        if (msg.type === 'hello') {  // ask for each window's timing (protocol revision 5)
          msg.timing = true;
          if (msg.audio) L.format = msg.audio;
          data = JSON.stringify(msg);
        }
      } else if (this === L.ws && L.format) {
        const samples = data.byteLength / (L.format.format === 'float32' ? 4 : 2);
        const m = L.pending;
        L.pending = null;
        L.sends.push([performance.now(), samples, m ? m.at : null, m && m.samples === samples ? m.first : -1, m ? m.peak : 1]);
      }
      return super.send(data);
    }
  };

  // Hooks on the viewer's own objects once it exposes them (window.dimgestor.clock: the playout clock).
  const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (cb) => raf((ts) => { L.inRaf = true; try { cb(ts); } finally { L.inRaf = false; } });
  const hook = setInterval(() => {
    const api = window.dimgestor;
    if (!api || !api.clock) return;
    clearInterval(hook);
    const clock = api.clock, arrive = clock.arrive.bind(clock), time = clock.time.bind(clock);
    clock.arrive = (pts, now) => { L.arrive.push([pts, now * 1000]); return arrive(pts, now); };
    clock.time = (now) => {
      const t = time(now);
      if (L.inRaf && t !== null) L.shown.push([now * 1000, t]);
      return t;
    };
  }, 5);

  L.ping = () => { if (L.ws && L.ws.readyState === 1) L.ws.send(JSON.stringify({ type: 'ping', t: performance.now() })); };
  /** Everything recorded since the last take, emptied (so a long run is read in pieces). */
  L.take = () => {
    const out = { mic_rate: L.format && L.format.rate, sends: L.sends, texts: L.texts, arrive: L.arrive, shown: L.shown };
    L.sends = []; L.texts = []; L.arrive = []; L.shown = [];
    return out;
  };
})();
