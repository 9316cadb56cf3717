// One frame in flight on the GPU. WebGL's drawing calls return before the GPU has drawn, so a page that draws every
// frame it is handed can run ahead of a slow GPU: with software GL (SwiftShader on a 2-core CPU) a live stream at
// 25 FPS queued seconds of drawing, the picture fell further behind the sound with every frame, and Chromium waited
// ~30 s for the queue when the page closed. The player draws a frame only once the GPU has finished the one before
// (a fence polled on each animation frame); the frames that arrive meanwhile are skipped, the newest is drawn next.
export class FrameInFlight {
  constructor(gl) {
    this.gl = gl;
    this.sync = null;
    this.onDone = null;
  }

  // True when no frame is pending on the GPU; a pending one that has finished calls its onDone(performance time).
  // A fence of a context lost since (or lost and restored: the old fence is then invalid) holds nothing and counts
  // no frame: that frame was never drawn.
  poll() {
    if (this.sync === null) return true;
    const gl = this.gl;
    const lost = gl.isContextLost();
    const status = lost ? null : gl.getSyncParameter(this.sync, gl.SYNC_STATUS);
    if (status === gl.UNSIGNALED) return false;
    const done = status === gl.SIGNALED ? this.onDone : null;
    if (!lost) gl.deleteSync(this.sync);
    this.sync = null;
    this.onDone = null;
    done?.(performance.now());
    return true;
  }

  // After a frame's drawing calls: the GPU's end of them is what poll() waits for (nothing on a lost context).
  mark(onDone = null) {
    const gl = this.gl;
    this.sync = gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0);
    gl.flush();
    this.onDone = this.sync === null ? null : onDone;
  }
}
