// The page as a live microphone (`geoavatar speak RUN --microphone --view`, manifest live: "speak").
//
// getUserMedia (no echo cancellation, noise suppression or gain control: the voice model hears what the microphone
// hears), then an AudioWorklet (WORKLET_SOURCE, loaded from a blob: the bundle stays one file) mixes to mono,
// resamples the context's rate (44.1 or 48 kHz, whatever the device runs at) to 16 kHz with a windowed-sinc
// low-pass (cut-off at 8 kHz, +-32 output samples wide: flat to the features' 7.6 kHz as a file's resampling is,
// what would alias below it under -40 dB; its taps computed once per phase), and posts 320-sample (20 ms) int16
// chunks with the
// audio-context time of each chunk's last sample. The page maps that time onto its own clock (the smallest
// receipt-minus-context-time offset of the last 5 s: the audio thread's messages arrive late, never early) and
// sends the chunk over the websocket (live.js: kind 2, capture time = performance.timeOrigin + that time).
export const OUT_RATE = 16000;
export const CHUNK_SAMPLES = 320; // 20 ms at 16 kHz
const OFFSET_WINDOW = 250; // chunks (5 s) over which the context-to-page clock offset is the smallest seen

// Runs in the AudioWorkletGlobalScope (globals sampleRate, currentTime, registerProcessor). Self-contained text:
// tests/test_web_sound.py runs it in node with those globals faked.
export const WORKLET_SOURCE = `
class GeoavatarMicrophone extends AudioWorkletProcessor {
  constructor(options) {
    super();
    const opts = (options && options.processorOptions) || {};
    this.outRate = opts.outRate || ${OUT_RATE};
    this.chunk = opts.chunk || ${CHUNK_SAMPLES};
    this.inRate = Math.round(sampleRate);
    this.ratio = this.inRate / this.outRate; // input samples per output sample
    this.cutoff = Math.min(0.5, 0.5 / this.ratio); // cycles per input sample
    this.half = Math.ceil(32 * Math.max(1, this.ratio)); // kernel half-width in input samples
    this.taps = new Map(); // phase -> the kernel at the input samples around an output sample of that phase
    this.buffer = new Float32Array(4096); // input samples from absolute index this.start
    this.start = 0;
    this.length = 0;
    this.produced = 0; // output samples made; the next one sits at input position produced * ratio
    this.out = new Int16Array(this.chunk);
    this.filled = 0;
  }

  kernel(d) { // windowed sinc (Hann) at distance d input samples, unnormalised
    if (Math.abs(d) >= this.half) return 0;
    const x = 2 * this.cutoff * d;
    const sinc = x === 0 ? 1 : Math.sin(Math.PI * x) / (Math.PI * x);
    return sinc * (0.5 + 0.5 * Math.cos(Math.PI * d / this.half));
  }

  tapsAt(phase) { // output sample at input position q + phase / outRate: the kernel over input samples base, ...
    let taps = this.taps.get(phase);
    if (!taps) {
      taps = [];
      const offset = this.half - (phase > 0 ? 1 : 0) + phase / this.outRate; // centre - base
      for (let d = offset; d > -this.half; d--) taps.push(this.kernel(d));
      taps = Float32Array.from(taps);
      this.taps.set(phase, taps);
    }
    return taps;
  }

  append(samples) {
    if (this.length + samples.length > this.buffer.length) {
      const grown = new Float32Array(Math.max(this.buffer.length * 2, this.length + samples.length));
      grown.set(this.buffer.subarray(0, this.length));
      this.buffer = grown;
    }
    this.buffer.set(samples, this.length);
    this.length += samples.length;
  }

  process(inputs) {
    const channels = inputs[0] || [];
    const frames = channels.length ? channels[0].length : 128; // no input (a stopped track): silence
    const quantumStart = this.start + this.length; // absolute input index of this quantum's first sample
    const mono = new Float32Array(frames);
    for (const channel of channels) for (let i = 0; i < frames; i++) mono[i] += channel[i] / channels.length;
    this.append(mono);
    const end = this.start + this.length; // absolute index after the newest input sample
    for (;;) {
      const exact = this.produced * this.inRate; // the centre times outRate, in integers: its phase is exact
      const whole = Math.floor(exact / this.outRate);
      const phase = exact - whole * this.outRate;
      const centre = whole + phase / this.outRate;
      if (centre + this.half >= end) break;
      let sum = 0;
      let weights = 0;
      const base = whole - this.half + (phase > 0 ? 1 : 0); // ceil(centre - half)
      const taps = this.tapsAt(phase);
      for (let k = Math.max(0, this.start - base); k < taps.length; k++) {
        sum += this.buffer[base + k - this.start] * taps[k];
        weights += taps[k];
      }
      const value = Math.max(-1, Math.min(1, weights > 0 ? sum / weights : 0)); // unit gain at 0 Hz
      this.out[this.filled++] = Math.round(value * 32767);
      this.produced += 1;
      if (this.filled === this.chunk) {
        // context time of the chunk's last sample: this quantum started at currentTime
        const time = currentTime + (centre - quantumStart) / sampleRate;
        this.port.postMessage({ samples: this.out.buffer, time }, [this.out.buffer]);
        this.out = new Int16Array(this.chunk);
        this.filled = 0;
      }
    }
    const keep = Math.floor(this.produced * this.ratio - this.half) - this.start; // samples no kernel needs again
    if (keep > 0) {
      this.buffer.copyWithin(0, keep, this.length);
      this.length -= keep;
      this.start += keep;
    }
    return true;
  }
}
registerProcessor("geoavatar-microphone", GeoavatarMicrophone);
`;

function describe(error) {
  return error && error.name ? `${error.name}: ${error.message}` : String(error);
}

export class Microphone {
  // onChunk(int16 samples [320], capture time in Unix seconds), onError(one line), onStatus(one line).
  constructor({ onChunk, onError, onStatus }) {
    this.onChunk = onChunk;
    this.onError = onError;
    this.onStatus = onStatus;
    this.offsets = []; // receipt time - context time (ms), the last OFFSET_WINDOW chunks
    this.chunks = 0;
    this.stopped = false; // stop() came: a start() still waiting (the permission prompt) must not open it after
  }

  async start() {
    let stream;
    try {
      if (!navigator.mediaDevices?.getUserMedia) {
        throw new Error("this page cannot use a microphone (not a secure context: open it on localhost or https)");
      }
      stream = await navigator.mediaDevices.getUserMedia({
        audio: { channelCount: 1, echoCancellation: false, noiseSuppression: false, autoGainControl: false },
      });
    } catch (error) {
      this.onError(`microphone: ${describe(error)}`);
      return false;
    }
    if (this.stopped) return this.release(stream);
    try {
      this.context = new AudioContext({ latencyHint: "interactive" });
      const url = URL.createObjectURL(new Blob([WORKLET_SOURCE], { type: "text/javascript" }));
      await this.context.audioWorklet.addModule(url);
      URL.revokeObjectURL(url);
      if (this.stopped) return this.release(stream);
      this.node = new AudioWorkletNode(this.context, "geoavatar-microphone", {
        numberOfInputs: 1, numberOfOutputs: 1, outputChannelCount: [1], channelCount: 1,
        channelCountMode: "explicit", channelInterpretation: "speakers",
        processorOptions: { outRate: OUT_RATE, chunk: CHUNK_SAMPLES },
      });
      this.node.port.onmessage = (event) => this.received(event.data);
      const mute = this.context.createGain(); // some browsers pull only nodes that reach the speakers
      mute.gain.value = 0;
      this.context.createMediaStreamSource(stream).connect(this.node).connect(mute).connect(this.context.destination);
    } catch (error) {
      for (const track of stream.getTracks()) track.stop();
      this.onError(`microphone: ${describe(error)}`);
      return false;
    }
    for (const track of stream.getAudioTracks()) {
      track.onended = () => this.onError("microphone: the microphone stopped");
    }
    this.stream = stream;
    if (this.context.state === "running") {
      this.onStatus("microphone on");
    } else {
      // the browser may hold the audio context until a click on this page; resume() then waits for one (never
      // awaited here: the page would hang before asking for the click)
      this.onStatus("click the page to start the microphone");
      this.context.onstatechange = () => {
        if (this.context?.state === "running") this.onStatus("microphone on");
      };
      const resume = () => this.context?.resume().catch(() => {});
      window.addEventListener("pointerdown", resume, { once: true });
      window.addEventListener("keydown", resume, { once: true });
      resume();
    }
    return true;
  }

  release(stream) { // stop() came while start() waited: nothing is left open
    for (const track of stream.getTracks()) track.stop();
    this.stop();
    return false;
  }

  received({ samples, time }) {
    const receivedMs = performance.now();
    this.offsets.push(receivedMs - time * 1000);
    if (this.offsets.length > OFFSET_WINDOW) this.offsets.shift();
    const offset = Math.min(...this.offsets);
    const captureMs = time * 1000 + offset; // on the page's clock (performance.now())
    this.chunks += 1;
    this.onChunk(new Int16Array(samples), (performance.timeOrigin + captureMs) / 1000);
  }

  stop() {
    this.stopped = true;
    for (const track of this.stream?.getTracks() ?? []) {
      track.onended = null;
      track.stop();
    }
    const context = this.context;
    this.context = null; // a second stop() (the track ended, then the socket closed) has nothing to close
    context?.close().catch(() => {});
  }
}
