// GeoAvatar's player: plays an exported clip (avatar.json + avatar.bin + clip.bin) or a live stream of posed
// vertices (a websocket of `geoavatar view` / `geoavatar drive --view`), posing every splat on the GPU.
//
// Per frame the CPU only turns the posed mesh into face frames (binding.js) and uploads them; the splats are
// placed, rotated, scaled and shaded by the generator (generator.js) and sorted by Spark.
//
// A clip with sound (manifest clip.audio) plays it and takes the shown frame from it (sound.js): while playing, frame
// = floor(audio.currentTime * fps), clamped to the clip. When the browser refuses to start the sound without a click
// (autoplay), the page says "press Play for sound" and waits, paused, on frame 0.
//
// Deep link: index.html?frame=N&paused=1&view=dataset draws clip frame N from the dataset camera at the dataset
// image size; document.body.dataset.drawnFrame = "N" once that frame is drawn with its splats sorted.
// window.geoavatar.stats: counters for tests and benchmarks (docs/web_player.md): drawn (frames handed to WebGL),
// finished (frames the GPU has finished drawing), received, frameCostMs,
// costs, transportMs; with sound audioTime (the sound's clock, seconds), audioFrame (the frame shown for it),
// audioBlocked; live "speak" microphoneChunks, microphoneError, soundToPictureMs and soundToPicture {count, p50,
// p95} (ms from a sound chunk's capture to the GPU's end of drawing the first mesh posed from it).
//
// At most one frame is in flight on the GPU (inflight.js): a slow GPU skips frames instead of queueing them.
import * as THREE from "three";
import { SparkRenderer } from "@sparkjsdev/spark";
import { faceFrames, dequantiseFrame, FACE_STRIDE } from "./binding.js";
import { avatarGenerator, floatTexture, halfTexture, FACE_TEXELS, POSE_TEXELS, ROW_TEXELS } from "./generator.js";
import { clamp, fittedIntrinsics, orbitWorld, placeCamera, projectionFromIntrinsics, worldFromViewmat } from "./camera.js";
import { FrameInFlight } from "./inflight.js";
import { LiveLink } from "./live.js";
import { buildControls } from "./controls.js";
import { ClipSound } from "./sound.js";

const FREE_YAW = [-180, 180];
const FREE_PITCH = [-89, 89];
const COST_WINDOW = 120; // frames in the rolling mean of the per-frame cost
const LATENCY_WINDOW = 1000; // drawn speech meshes in stats.soundToPictureMs
const FORMAT = 2; // the avatar.json / avatar.bin layout this page reads (geoavatar/web/pack.py FORMAT_VERSION)

async function fetchBytes(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  return response.arrayBuffer();
}

async function loadAvatar(base) {
  const manifestResponse = await fetch(new URL("avatar.json", base));
  if (!manifestResponse.ok) throw new Error(`avatar.json: HTTP ${manifestResponse.status}`);
  const manifest = await manifestResponse.json();
  if (manifest.format !== FORMAT) {
    throw new Error(`avatar.json: format ${manifest.format}, this player reads ${FORMAT}: export the avatar again`);
  }
  const audio = manifest.clip.audio; // absent: a clip without sound (and every folder written before sound)
  if (audio && !(audio.rate > 0 && audio.seconds > 0 && typeof audio.file === "string")) {
    throw new Error("avatar.json: clip.audio invalid");
  }
  const [avatarBytes, clipBytes, audioBytes] = await Promise.all([
    fetchBytes(new URL(manifest.avatar.file, base)),
    fetchBytes(new URL(manifest.clip.file, base)),
    audio ? fetchBytes(new URL(audio.file, base)) : null,
  ]);
  const { splats, faces, vertices, followsHead } = manifest.avatar;
  const posed = followsHead ? manifest.avatar.posed : 0; // the first `posed` splats carry a pose row
  if (!Number.isInteger(posed) || posed < 0 || posed > splats) throw new Error("avatar.json: avatar.posed invalid");
  const rowStart = splats * 16; // float32 x 4 a splat
  const faceStart = rowStart + splats * ROW_TEXELS * 8; // float16 x 20 a splat
  const poseStart = faceStart + faces * 12;
  if (avatarBytes.byteLength !== poseStart + posed * POSE_TEXELS * 8) throw new Error("avatar.bin: unexpected size");
  const anchors = new Float32Array(avatarBytes, 0, splats * 4);
  const rows = new Uint16Array(avatarBytes, rowStart, splats * ROW_TEXELS * 4);
  const faceIds = new Uint32Array(avatarBytes, faceStart, faces * 3);
  const poses = followsHead ? new Uint16Array(avatarBytes, poseStart, posed * POSE_TEXELS * 4) : null;
  const clip = new Uint16Array(clipBytes);
  if (clip.length !== manifest.clip.frames * vertices * 3) throw new Error("clip.bin: unexpected size");
  if (followsHead && manifest.clip.pose?.length !== manifest.clip.frames) {
    throw new Error("avatar.json: clip.pose missing");
  }
  return { manifest, anchors, rows, faceIds, poses, clip, audioBytes };
}

function readOptions() {
  const query = new URLSearchParams(window.location.search);
  const frame = query.get("frame");
  return {
    frame: frame === null ? null : Math.max(0, parseInt(frame, 10) || 0),
    paused: query.get("paused") === "1",
    datasetView: query.get("view") === "dataset",
  };
}

class Player {
  constructor({ manifest, anchors, rows, faceIds, poses, clip, audioBytes }, options) {
    this.manifest = manifest;
    this.options = options;
    this.clip = clip;
    this.faceIds = faceIds;
    this.vertexCount = manifest.avatar.vertices;
    this.frameCount = manifest.clip.frames;
    this.vertices = new Float32Array(this.vertexCount * 3);
    this.stats = { drawn: 0, finished: 0, received: 0, lastReceived: -1, frameCostMs: 0, costs: [], ready: false };
    this.frame = Math.min(options.frame ?? 0, this.frameCount - 1);
    this.playing = !options.paused && this.frameCount > 1;
    this.orbit = { yaw: 0, pitch: 0, distance: 1, free: false };
    this.liveVertices = null; // the newest streamed mesh, shown instead of the clip while set
    this.liveCode = null; // its head pose code [6] when the hair follows the head
    this.liveCapture = null; // the capture time (Unix s) of the sound its mesh was posed from, until it is drawn
    this.statusText = "";
    this.sound = audioBytes ? new ClipSound(audioBytes, { fps: manifest.clip.fps, frames: this.frameCount,
      seconds: manifest.clip.audio.seconds }) : null;
    if (this.sound) {
      Object.assign(this.stats, { audioTime: 0, audioFrame: this.frame, audioBlocked: false });
      this.sound.element.addEventListener("pause", () => { // paused from outside the page (media keys, ...)
        if (this.playing) this.setPlaying(false);
      });
      this.sound.element.addEventListener("play", () => { // and played from outside: the picture follows it
        if (!this.playing) this.setPlaying(true);
      });
    }
    this.needsDraw = true;
    this.dirtyFrame = true;
    this.setupRenderer();
    this.setupSplats(anchors, rows, poses);
  }

  setupRenderer() {
    this.renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    // the dataset view is pixel for pixel; elsewhere at most 2 device pixels a CSS pixel (phones report 3)
    this.renderer.setPixelRatio(this.options.datasetView ? 1 : Math.min(window.devicePixelRatio, 2));
    document.getElementById("stage").appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera();
    this.spark = new SparkRenderer({
      renderer: this.renderer,
      accumExtSplats: true, // float32 centres, half-float scales and colours: no visible quantisation
      maxStdDev: 3.33, // the CPU renderer's +-3.33 sigma footprint
      preBlurAmount: 0.3, // gsplat's 0.3 px dilation, without opacity compensation
      blurAmount: 0.0,
      minAlpha: 1 / 255,
      sortRadial: false, // depth order along the view axis, as the CPU renderer
      enableLod: false,
      onDirty: () => { this.needsDraw = true; },
    });
    this.scene.add(this.spark);
    this.inFlight = new FrameInFlight(this.renderer.getContext());
    this.setBackground(this.manifest.background);
    this.resize();
    window.addEventListener("resize", () => this.resize());
  }

  setupSplats(anchors, rows, poses) {
    const { splats, faces, shading, posed } = this.manifest.avatar;
    this.anchorTexture = floatTexture(splats);
    this.anchorTexture.image.data.set(anchors);
    this.rowTexture = halfTexture(splats * ROW_TEXELS);
    this.rowTexture.image.data.set(rows);
    this.faceTexture = floatTexture(faces * FACE_TEXELS);
    this.faceData = this.faceTexture.image.data.subarray(0, faces * FACE_STRIDE);
    if (poses) {
      this.poseTexture = halfTexture(Math.max(1, posed) * POSE_TEXELS);
      this.poseTexture.image.data.set(poses);
    }
    this.generator = avatarGenerator({ count: splats, anchors: this.anchorTexture, rows: this.rowTexture,
      faces: this.faceTexture, shading, poses: this.poseTexture, posed });
    this.generator.frustumCulled = false;
    this.scene.add(this.generator);
  }

  setBackground(rgb) {
    this.background = rgb;
    this.renderer.setClearColor(new THREE.Color().setRGB(rgb[0], rgb[1], rgb[2], THREE.SRGBColorSpace), 1);
    this.needsDraw = true;
  }

  // The view: the dataset camera (deep link) or the orbit about the head centre.
  resize() {
    const { camera: cam } = this.manifest;
    if (this.options.datasetView) {
      this.renderer.setSize(cam.width, cam.height);
      this.placeDatasetCamera();
    } else {
      const stage = document.getElementById("stage");
      const width = stage.clientWidth || window.innerWidth;
      const height = stage.clientHeight || window.innerHeight;
      this.renderer.setSize(width, height);
      this.viewSize = [width, height];
      this.placeOrbit();
    }
    this.needsDraw = true;
  }

  // The dataset camera of the shown frame (a clip whose cameras move lists one per frame).
  placeDatasetCamera() {
    const { camera: cam, viewmats } = this.manifest;
    const viewmat = viewmats ? viewmats[this.frame] : cam.viewmat;
    placeCamera(this.camera, worldFromViewmat(viewmat), projectionFromIntrinsics(cam.K, cam.width, cam.height));
    this.needsDraw = true;
  }

  orbitLimits() {
    const limits = this.manifest.orbit;
    return this.orbit.free ? { yaw: FREE_YAW, pitch: FREE_PITCH } : { yaw: limits.yaw, pitch: limits.pitch };
  }

  placeOrbit() {
    if (this.options.datasetView) return;
    const { camera: cam, orbit } = this.manifest;
    const limits = this.orbitLimits();
    this.orbit.yaw = clamp(this.orbit.yaw, limits.yaw);
    this.orbit.pitch = clamp(this.orbit.pitch, limits.pitch);
    const [width, height] = this.viewSize;
    const K = fittedIntrinsics(cam.K, cam.height, width, height);
    const c2w = orbitWorld(cam.viewmat, orbit.centre, this.orbit.yaw, this.orbit.pitch, this.orbit.distance);
    placeCamera(this.camera, c2w, projectionFromIntrinsics(K, width, height));
    this.needsDraw = true;
  }

  // Face frames of the shown mesh into the face texture (the per-frame CPU work the page measures).
  uploadFrame() {
    const started = performance.now();
    const mesh = this.liveVertices ?? dequantiseFrame(this.clip, this.frame, this.vertexCount,
      this.manifest.clip.offset, this.manifest.clip.step, this.vertices);
    faceFrames(mesh, this.faceIds, this.faceData);
    if (this.poseTexture) {
      this.generator.setPoseCode(this.liveVertices ? this.liveCode : this.manifest.clip.pose[this.frame]);
    }
    this.faceTexture.needsUpdate = true;
    this.renderer.initTexture(this.faceTexture); // upload now, inside the measured span
    this.generator.updateVersion();
    const costs = this.stats.costs;
    costs.push(performance.now() - started);
    if (costs.length > COST_WINDOW) costs.shift();
    this.stats.frameCostMs = costs.reduce((a, b) => a + b, 0) / costs.length;
    this.dirtyFrame = false;
    this.needsDraw = true;
  }

  showFrame(frame) {
    this.frame = ((frame % this.frameCount) + this.frameCount) % this.frameCount;
    this.dirtyFrame = true;
    this.controls?.showFrame(this.frame);
    if (this.sound && !this.playing) this.sound.seek(this.frame); // Play goes on from here
    if (this.options.datasetView && this.manifest.viewmats) this.placeDatasetCamera();
    if (this.live?.editing) this.live.resendEdit(); // the edit follows the shown frame
  }

  showLive(vertices, code = null, capture = null) {
    this.liveVertices = vertices;
    this.liveCode = code;
    this.liveCapture = capture;
    this.dirtyFrame = true;
  }

  // A mesh posed from sound is drawn (`drawnAt`, performance time): how long after its newest sound chunk's capture.
  recordSoundLatency(capture, drawnAt) {
    const ms = performance.timeOrigin + drawnAt - capture * 1000;
    const window_ = this.stats.soundToPictureMs;
    window_.push(ms);
    if (window_.length > LATENCY_WINDOW) window_.shift();
    const sorted = [...window_].sort((a, b) => a - b);
    const at = (q) => sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
    this.stats.soundToPicture = { count: sorted.length, p50: at(0.5), p95: at(0.95) };
  }

  setStatus(text) {
    this.statusText = text;
    this.controls?.setStatus(text);
  }

  // Draw once the generated splats are sorted: Spark's update() generates and awaits its sort.
  async drawSettled() {
    for (let i = 0; i < 8; i++) {
      await this.spark.update({ scene: this.scene, camera: this.camera });
      if (!this.spark.sorting && !this.spark.sortDirty) break;
    }
    while (!this.inFlight.poll()) await new Promise((resolve) => requestAnimationFrame(resolve));
    this.needsDraw = false;
    this.renderFrame();
  }

  // Hand the frame to WebGL and fence it (inFlight.poll() has said the GPU is free); `onDrawn(performance time)`
  // once the GPU has drawn it.
  renderFrame(onDrawn = null) {
    this.renderer.render(this.scene, this.camera);
    this.stats.drawn += 1;
    this.inFlight.mark((drawnAt) => {
      this.stats.finished += 1;
      onDrawn?.(drawnAt);
    });
  }

  async start() {
    this.sound?.seek(this.frame);
    this.uploadFrame();
    await this.drawSettled();
    document.body.dataset.drawnFrame = String(this.frame);
    this.stats.ready = true;
    this.controls = buildControls(this);
    this.clockOrigin = performance.now() - (this.frame / this.manifest.clip.fps) * 1000;
    requestAnimationFrame((t) => this.tick(t));
    if (this.sound && this.playing) this.playSound();
  }

  // Start the sound (the clip's clock); refused (no click yet): paused on frame 0 with a status line.
  async playSound() {
    const refusal = await this.sound.play();
    if (refusal === null) {
      this.stats.audioBlocked = false;
      if (this.statusText === "press Play for sound") this.setStatus("");
    } else if (refusal === "NotAllowedError") {
      this.stats.audioBlocked = true;
      this.setPlaying(false);
      this.showFrame(0);
      this.setStatus("press Play for sound");
      console.info("GeoAvatar player: the browser starts sound only after a click: press Play for sound");
    } else if (refusal !== "AbortError") { // AbortError: paused again before it started
      this.setPlaying(false);
      this.setStatus(`sound: ${refusal}`);
    }
  }

  tick(now) {
    requestAnimationFrame((t) => this.tick(t));
    if (this.settling) return;
    if (this.playing && !this.liveVertices) {
      let frame;
      if (this.sound) { // the sound is the clock: it loops, and so does the clip
        const time = this.sound.time;
        frame = this.sound.frameAt(time);
        this.stats.audioTime = time;
        this.stats.audioFrame = frame;
      } else {
        frame = Math.floor(((now - this.clockOrigin) / 1000) * this.manifest.clip.fps) % this.frameCount;
      }
      if (frame !== this.frame) this.showFrame(frame);
    }
    if (!this.playing && this.dirtyFrame && !this.liveVertices) {
      // a still frame (paused, scrubbed): drawn once its splats are sorted, then announced
      this.settling = true;
      const frame = this.frame; // the frame uploaded now (a scrub meanwhile is drawn next, and announced then)
      this.uploadFrame();
      this.drawSettled().then(() => {
        document.body.dataset.drawnFrame = String(frame);
        this.settling = false;
      });
      return;
    }
    if (!this.inFlight.poll()) return; // the GPU is still drawing the last frame: the newest is drawn after it
    if (this.dirtyFrame) this.uploadFrame();
    if (this.needsDraw) {
      this.needsDraw = false;
      const capture = this.liveVertices ? this.liveCapture : null;
      this.liveCapture = null;
      this.renderFrame(capture === null ? null : (drawnAt) => this.recordSoundLatency(capture, drawnAt));
    }
  }

  setPlaying(playing) {
    const wasPlaying = this.playing;
    this.playing = playing && this.frameCount > 1;
    this.clockOrigin = performance.now() - (this.frame / this.manifest.clip.fps) * 1000;
    this.controls?.showPlaying(this.playing);
    if (!this.sound) return;
    if (this.playing) {
      if (this.sound.frameAt() !== this.frame) this.sound.seek(this.frame);
      this.playSound();
    } else {
      this.sound.pause(); // where the sound stopped: its frame is shown, and Play goes on from there
      const frame = this.sound.frameAt();
      if (wasPlaying && frame !== this.frame && !this.liveVertices) {
        this.frame = frame;
        this.dirtyFrame = true;
        this.controls?.showFrame(frame);
      }
      this.stats.audioTime = this.sound.time;
      this.stats.audioFrame = this.frame;
    }
  }
}

async function main() {
  const status = document.getElementById("status");
  try {
    const options = readOptions();
    const player = new Player(await loadAvatar(window.location.href), options);
    window.geoavatar = { player, stats: player.stats, faceFrames };
    if (player.manifest.live) player.live = new LiveLink(player, player.manifest.live === "speak");
    await player.start();
    status.textContent = "";
  } catch (error) {
    status.textContent = `GeoAvatar player: ${error.message}`;
    document.body.dataset.error = error.message;
    throw error;
  }
}

main();
