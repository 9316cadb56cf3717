// A clip's sound (manifest clip.audio, audio.wav): an <audio> element (id "sound") that is the clip's clock.
//
// While the clip plays, the shown frame is floor(audio.currentTime * fps), clamped to the clip: picture and sound
// cannot drift apart, whatever rate the page draws at. The sound loops, so the clip restarts where the sound ends.
// The WAV is fetched with the other files and played from a blob: URL, which every browser can seek in (a plain
// static server such as python's http.server answers no byte ranges, and without them a browser may refuse to
// seek a media file it streams).
const FRAME_EPSILON = 1e-4; // frames: a seek to frame N's time, rounded to microseconds, still reads as frame N

export class ClipSound {
  constructor(bytes, { fps, frames, seconds }) {
    this.fps = fps;
    this.frames = frames;
    this.seconds = seconds;
    // the last frame the sound reaches (a looping element reads its full duration for a moment before it wraps)
    this.lastFrame = Math.max(0, Math.min(frames, Math.ceil(seconds * fps - FRAME_EPSILON)) - 1);
    this.element = document.createElement("audio");
    this.element.id = "sound";
    this.element.preload = "auto";
    this.element.loop = true;
    this.element.src = URL.createObjectURL(new Blob([bytes], { type: "audio/wav" }));
    document.body.appendChild(this.element); // no controls attribute: not drawn
  }

  get time() {
    return this.element.currentTime;
  }

  get paused() {
    return this.element.paused;
  }

  // The clip frame the sound is at (the clip ends where the sound does).
  frameAt(time = this.element.currentTime) {
    return Math.min(this.lastFrame, Math.max(0, Math.floor(time * this.fps + FRAME_EPSILON)));
  }

  // Put the sound at the start of clip frame `frame` (a frame past the sound's end: its start).
  seek(frame) {
    const time = frame / this.fps;
    this.element.currentTime = time < this.seconds ? time : 0;
  }

  // Start the sound; resolves null once it plays, else the refusal: "NotAllowedError" (the browser wants a click
  // first: autoplay), "AbortError" (paused again before it started), or another error's name and message.
  async play() {
    try {
      await this.element.play();
      return null;
    } catch (error) {
      const name = error?.name;
      return name === "NotAllowedError" || name === "AbortError" ? name : `${name}: ${error?.message}`;
    }
  }

  pause() {
    this.element.pause();
  }
}
