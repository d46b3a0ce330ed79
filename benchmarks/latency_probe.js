// Injected by benchmarks/latency.py before the web viewer loads (Page.addScriptToEvaluateOnNewDocument): stamps,
// on the page's performance.now(), every step of the Talk path that the page sees, without changing the viewer.
// The viewer's socket and microphone chunks live in its socket worker (clients/web/socket-worker.js): the probe
// starts that worker with its own worker part first (stamps there are put on the page's clock through
// performance.timeOrigin), which reports to this part at each ping.
//   sends   each audio message sent: [time, samples, when its microphone chunk reached the worker, the chunk's
//           first sample above ONSET or -1, the chunk's peak |x|]
//   texts   `timing` and `pong` messages (arrival, JSON); the viewer's hello asks for `timing`
//   arrive  each frame the playout clock is told of (pts, arrival as the worker stamped it)
//   shown   each requestAnimationFrame's presented time (rAF time, pts presented by the playout clock)
(() => {
  const L = window.__latency = { sends: [], texts: [], arrive: [], shown: [], format: null, worker: null,
                                 inRaf: false };

  /** The probe's part inside the socket worker, run before the worker's own module. */
  function workerPart(pageOrigin) {
    const ONSET = 0.05;  // an onset: the first sample above this after quiet chunks (latency.py says how quiet)
    const shift = performance.timeOrigin - pageOrigin;
    const now = () => performance.now() + shift;
    const W = { sends: [], texts: [], format: null, pending: null, ws: null };
    self.addEventListener('message', (e) => {  // before the worker's own onmessage, which never sees these
      if (!(e.data && e.data.__latency === 'ping')) return;
      e.stopImmediatePropagation();
      if (W.ws && W.ws.readyState === 1) W.ws.send(JSON.stringify({ type: 'ping', t: now() }));
      self.postMessage({ __latency: { sends: W.sends, texts: W.texts, format: W.format } });
      W.sends = [];
      W.texts = [];
    });
    // The microphone's chunks come on a MessagePort whose onmessage the worker sets: stamp each as it comes.
    const handler = Object.getOwnPropertyDescriptor(MessagePort.prototype, 'onmessage');
    Object.defineProperty(MessagePort.prototype, 'onmessage', {
      configurable: true,
      get() { return handler.get.call(this); },
      set(h) {
        handler.set.call(this, typeof h !== 'function' ? h : (e) => {
          const x = e.data;
          if (x instanceof Float32Array) {
            let first = -1, peak = 0;  // the first sample above ONSET, and the chunk's peak
            for (let i = 0; i < x.length; i++) {
              const a = Math.abs(x[i]);
              if (a > ONSET && first < 0) first = i;
              peak = Math.max(peak, a);
            }
            W.pending = { at: now(), samples: x.length, first, peak };
          }
          return h.call(this, e);
        });
      },
    });
    const Socket = self.WebSocket;
    self.WebSocket = class extends Socket {
      constructor(...args) {
        super(...args);
        W.ws = this;
        this.addEventListener('message', (e) => {
          if (typeof e.data === 'string' && (e.data.includes('"timing"') || e.data.includes('"pong"')))
            W.texts.push([now(), e.data]);
        });
      }
      send(data) {
        if (typeof data === 'string') {
          const msg = JSON.parse(data);
          if (msg.type === 'hello') {  // ask for each window's timing (protocol revision 5)
            msg.timing = true;
            if (msg.audio) W.format = msg.audio;
            data = JSON.stringify(msg);
          }
        } else if (this === W.ws && W.format) {
          const samples = data.byteLength / (W.format.format === 'float32' ? 4 : 2);
          const m = W.pending;
          W.pending = null;
          W.sends.push([now(), samples, m ? m.at : null, m && m.samples === samples ? m.first : -1, m ? m.peak : 1]);
        }
        return super.send(data);
      }
    };
  }

  const PageWorker = window.Worker;
  window.Worker = class extends PageWorker {
    constructor(url, options) {
      const href = new URL(url, location.href).href;
      if (!href.endsWith('/socket-worker.js')) { super(url, options); return; }
      // Static imports, the probe's first: both run before the worker takes any message (an `await import` would
      // let the page's first messages reach the worker before its own onmessage exists).
      const blob = (text) => URL.createObjectURL(new Blob([text], { type: 'text/javascript' }));
      const probe = blob(`(${workerPart})(${performance.timeOrigin});\n`);
      super(blob(`import ${JSON.stringify(probe)};\nimport ${JSON.stringify(href)};\n`), { ...options, type: 'module' });
      L.worker = this;
      this.addEventListener('message', (e) => {  // registered before the viewer's onmessage, which never sees it
        if (!(e.data && e.data.__latency)) return;
        e.stopImmediatePropagation();
        const part = e.data.__latency;
        L.sends.push(...part.sends);
        L.texts.push(...part.texts);
        L.format = part.format || L.format;
      });
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

  /** A ping on the viewer's socket (the worker stamps it); the worker's stamps come back with the answer. */
  L.ping = () => { if (L.worker) L.worker.postMessage({ __latency: 'ping' }); };
  /** Everything recorded since the last take, emptied (so a long run is read in pieces). */
  L.take = () => {
    const out = { mic_rate: L.format && L.format.rate, sends: L.sends, texts: L.texts, arrive: L.arrive, shown: L.shown };
    L.sends = []; L.texts = []; L.arrive = []; L.shown = [];
    return out;
  };
})();
