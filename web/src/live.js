// The websocket link of a live player (`geoavatar view`, `geoavatar drive --view`).
//
// Server -> page, binary: a 16-byte header (uint32 kind = 1, uint32 sequence number, float64 send time in Unix
// seconds) and float32 posed vertices [V * 3], then the head pose code [6] when the avatar's hair follows the head
// (geoavatar/web/pack.py). Page -> server, text JSON: {"type": "edit", "frame": clip frame,
// "expr": [...], "jaw": radians, "yaw", "pitch": degrees} (view's sliders; all zero = no edit: the page plays its clip
// again).
const HEADER_BYTES = 16;
const KIND_VERTICES = 1;

export class LiveLink {
  constructor(player) {
    this.player = player;
    this.stats = player.stats;
    this.stats.transportMs = [];
    const url = new URL("ws", window.location.href);
    url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
    this.socket = new WebSocket(url);
    this.socket.binaryType = "arraybuffer";
    this.socket.onmessage = (event) => this.receive(event.data);
    this.socket.onclose = () => { this.player.controls?.setStatus("live stream closed"); };
    this.editing = false;
  }

  receive(data) {
    if (!(data instanceof ArrayBuffer) || data.byteLength < HEADER_BYTES) return;
    const header = new DataView(data, 0, HEADER_BYTES);
    if (header.getUint32(0, true) !== KIND_VERTICES) return;
    const sequence = header.getUint32(4, true);
    const sent = header.getFloat64(8, true);
    const count = this.player.vertexCount * 3;
    const follows = Boolean(this.player.manifest.avatar.followsHead);
    if (data.byteLength !== HEADER_BYTES + 4 * (count + (follows ? 6 : 0))) return;
    const vertices = new Float32Array(data, HEADER_BYTES, count);
    const code = follows ? new Float32Array(data, HEADER_BYTES + 4 * count, 6) : null;
    this.stats.received += 1;
    this.stats.lastReceived = sequence;
    this.stats.transportMs.push(Date.now() - sent * 1000);
    if (this.stats.transportMs.length > 1000) this.stats.transportMs.shift();
    if (this.player.manifest.live === "drive" || this.editing) this.player.showLive(vertices, code);
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
}
