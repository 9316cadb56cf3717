// The websocket link of a live player (`geoavatar view`, `geoavatar drive --view`, `geoavatar speak --microphone
// --view`). All binary messages are little-endian; geoavatar/web/live.py is the other end.
//
// Server -> page, binary:
//   kind 1, a posed mesh: a 16-byte header (uint32 kind = 1, uint32 sequence number, float64 send time in Unix
//     seconds) and float32 posed vertices [V * 3], then the head pose code [6] when the avatar's hair follows the
//     head (geoavatar/web/pack.py).
//   kind 3, a mesh posed from the microphone's sound: a 24-byte header (uint32 kind = 3, uint32 sequence number,
//     float64 send time, float64 capture time: the capture time, echoed back, of the newest sound chunk the mesh was
//     posed from), then the vertices and code as kind 1. Once drawn, the page records drawn time - capture time
//     (stats.soundToPictureMs, stats.soundToPicture {count, p50, p95}, ms), both times on the page's clock.
// Page -> server, binary (live "speak" only):
//   kind 2, ~20 ms of the microphone: a 16-byte header (uint32 kind = 2, uint32 sequence number from 0, float64
//     capture time in Unix seconds by the page's clock, (performance.timeOrigin + the capture's performance time)
//     / 1000, of the chunk's last sample), then int16 samples, 16 kHz mono (microphone.js).
// Page -> server, text JSON:
//   {"type": "edit", "frame": clip frame, "expr": [...], "jaw": radians, "yaw", "pitch": degrees} (view's sliders;
//     all zero = no edit: the page plays its clip again);
//   {"type": "microphone", "error": "NotAllowedError: Permission denied"} when the page cannot be the microphone
//     (getUserMedia failed: none, permission refused) or it stopped; the server says so in one line and stops.
import { Microphone } from "./microphone.js";

const HEADER_BYTES = 16;
const SOUND_HEADER_BYTES = 24;
const KIND_VERTICES = 1;
const KIND_AUDIO = 2;
const KIND_SOUND_VERTICES = 3;
const TRANSPORT_WINDOW = 1000;

export class LiveLink {
  constructor(player, microphone = false) {
    this.player = player;
    this.stats = player.stats;
    this.stats.transportMs = [];
    this.stats.soundToPictureMs = [];
    this.stats.soundToPicture = { count: 0, p50: null, p95: null };
    const url = new URL("ws", window.location.href);
    url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
    this.socket = new WebSocket(url);
    this.socket.binaryType = "arraybuffer";
    this.socket.onmessage = (event) => this.receive(event.data);
    this.socket.onclose = () => {
      this.microphone?.stop();
      this.player.setStatus(this.stats.microphoneError ?? "live stream closed"); // the page's one line stays
    };
    this.editing = false;
    if (microphone) {
      Object.assign(this.stats, { microphoneChunks: 0, microphoneError: null });
      this.audioSequence = 0;
      this.socket.onopen = () => this.startMicrophone();
    }
  }

  receive(data) {
    if (!(data instanceof ArrayBuffer) || data.byteLength < HEADER_BYTES) return;
    const header = new DataView(data);
    const kind = header.getUint32(0, true);
    if (kind !== KIND_VERTICES && kind !== KIND_SOUND_VERTICES) return;
    const start = kind === KIND_VERTICES ? HEADER_BYTES : SOUND_HEADER_BYTES;
    const sequence = header.getUint32(4, true);
    const sent = header.getFloat64(8, true);
    const count = this.player.vertexCount * 3;
    const follows = Boolean(this.player.manifest.avatar.followsHead);
    if (data.byteLength !== start + 4 * (count + (follows ? 6 : 0))) return;
    const capture = kind === KIND_SOUND_VERTICES ? header.getFloat64(16, true) : null;
    const vertices = new Float32Array(data, start, count);
    const code = follows ? new Float32Array(data, start + 4 * count, 6) : null;
    this.stats.received += 1;
    this.stats.lastReceived = sequence;
    this.stats.transportMs.push(Date.now() - sent * 1000);
    if (this.stats.transportMs.length > TRANSPORT_WINDOW) this.stats.transportMs.shift();
    const { live } = this.player.manifest;
    if (live === "drive" || live === "speak" || this.editing) this.player.showLive(vertices, code, capture);
  }

  // view's sliders: ask Python for the shown clip frame with these edits (none: back to the clip).
  sendEdit(expr, jaw, yaw = 0, pitch = 0) {
    this.edit = { expr, jaw, yaw, pitch };
    this.editing = [...expr, jaw, yaw, pitch].some((v) => v !== 0);
    if (this.editing) this.player.setPlaying(false);
    else this.player.showLive(null);
    this.resendEdit();
  }

  resendEdit() {
    if (!this.editing || this.socket.readyState !== WebSocket.OPEN) return; // no edit: the clip plays by itself
    this.socket.send(JSON.stringify({ type: "edit", frame: this.player.frame, ...this.edit }));
  }

  // live "speak": the page's microphone, 20 ms chunks at 16 kHz, once the socket is open.
  async startMicrophone() {
    this.microphone = new Microphone({
      onChunk: (samples, capture) => this.sendAudio(samples, capture),
      onError: (text) => this.microphoneFailed(text),
      onStatus: (text) => this.player.setStatus(text),
    });
    this.player.setStatus("asking for the microphone");
    await this.microphone.start();
  }

  sendAudio(samples, capture) {
    if (this.socket.readyState !== WebSocket.OPEN) return;
    const message = new ArrayBuffer(HEADER_BYTES + 2 * samples.length);
    const view = new DataView(message);
    view.setUint32(0, KIND_AUDIO, true);
    view.setUint32(4, this.audioSequence, true);
    view.setFloat64(8, capture, true);
    for (let i = 0; i < samples.length; i++) view.setInt16(HEADER_BYTES + 2 * i, samples[i], true);
    this.socket.send(message);
    this.audioSequence = (this.audioSequence + 1) >>> 0;
    this.stats.microphoneChunks += 1;
  }

  microphoneFailed(text) {
    if (this.stats.microphoneError) return; // one line, once
    this.stats.microphoneError = text;
    this.player.setStatus(text);
    this.microphone?.stop();
    if (this.socket.readyState === WebSocket.OPEN) {
      this.socket.send(JSON.stringify({ type: "microphone", error: text }));
    }
  }
}
