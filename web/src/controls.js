// The page's controls: play/pause, scrub (both move the clip's sound too, player.js), background colour, the orbit
// (drag to turn, wheel to zoom, limited to the head turns the training video covered unless "free orbit" is
// ticked), a one-line status (#live-status: "press Play for sound", the live stream's and the microphone's state),
// and view's edit sliders.
const DRAG_DEGREES_PER_PIXEL = 0.3;

function element(tag, attributes = {}, parent = null) {
  const node = document.createElement(tag);
  Object.assign(node, attributes);
  if (parent) parent.appendChild(node);
  return node;
}

function hexColour(rgb) {
  return "#" + rgb.map((v) => Math.round(Math.min(1, Math.max(0, v)) * 255).toString(16).padStart(2, "0")).join("");
}

function rgbOf(hex) {
  return [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
}

export function buildControls(player) {
  const bar = document.getElementById("controls");
  const { manifest } = player;
  const play = element("button", { id: "play", textContent: player.playing ? "Pause" : "Play" }, bar);
  const scrub = element("input", { id: "scrub", type: "range", min: 0, max: player.frameCount - 1, step: 1,
    value: player.frame }, bar);
  const label = element("span", { id: "frame-label" }, bar);
  const colour = element("input", { id: "background", type: "color", value: hexColour(manifest.background),
    title: "background colour" }, bar);
  const freeLabel = element("label", { title: "turn beyond the head turns the training video covered" }, bar);
  const free = element("input", { id: "free-orbit", type: "checkbox" }, freeLabel);
  freeLabel.append(" free orbit");
  const reset = element("button", { id: "reset-view", textContent: "Reset view" }, bar);
  const status = element("span", { id: "live-status", textContent: player.statusText }, bar); // one line
  const single = player.frameCount < 2 || manifest.live === "drive" || manifest.live === "speak";
  play.disabled = scrub.disabled = single;

  const controls = {
    showFrame(frame) {
      scrub.value = frame;
      label.textContent = `${frame + 1} / ${player.frameCount} · ${manifest.clip.fps} fps`;
    },
    setStatus(text) { status.textContent = text; },
    showPlaying(playing) { play.textContent = playing ? "Pause" : "Play"; },
  };
  controls.showFrame(player.frame);
  play.onclick = () => player.setPlaying(!player.playing);
  scrub.oninput = () => {
    player.setPlaying(false);
    player.showFrame(parseInt(scrub.value, 10));
  };
  colour.oninput = () => player.setBackground(rgbOf(colour.value));
  free.onchange = () => { player.orbit.free = free.checked; player.placeOrbit(); };
  reset.onclick = () => { Object.assign(player.orbit, { yaw: 0, pitch: 0, distance: 1 }); player.placeOrbit(); };
  bindOrbit(player, player.renderer.domElement);
  if (manifest.edit) buildEditSliders(player, document.getElementById("edits"));
  return controls;
}

function bindOrbit(player, canvas) {
  let last = null;
  canvas.addEventListener("pointerdown", (e) => { last = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { last = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (!last) return;
    // dragging right turns the camera to the left of the head, as dragging the head itself
    player.orbit.yaw -= (e.clientX - last[0]) * DRAG_DEGREES_PER_PIXEL;
    player.orbit.pitch += (e.clientY - last[1]) * DRAG_DEGREES_PER_PIXEL;
    last = [e.clientX, e.clientY];
    player.placeOrbit();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    player.orbit.distance = Math.min(4, Math.max(0.3, player.orbit.distance * Math.exp(e.deltaY * 0.001)));
    player.placeOrbit();
  }, { passive: false });
}

// `geoavatar view`: expression, jaw and head-turn sliders, posed in Python and streamed back.
function buildEditSliders(player, panel) {
  const { edit } = player.manifest;
  panel.hidden = false;
  const inputs = [];
  const add = (name, min, max, step) => {
    const row = element("label", { className: "edit" }, panel);
    row.append(name);
    const input = element("input", { type: "range", min, max, step, value: 0 }, row);
    inputs.push(input);
    return input;
  };
  const expr = edit.expressions.map((name) => add(name, -edit.exprRange, edit.exprRange, 0.05));
  const jaw = add("jaw open (rad)", edit.jawRange[0], edit.jawRange[1], 0.01);
  const yaw = add("head yaw (deg)", -edit.headRange, edit.headRange, 1);
  const pitch = add("head pitch (deg)", -edit.headRange, edit.headRange, 1);
  const send = () => player.live?.sendEdit(expr.map((i) => parseFloat(i.value)), parseFloat(jaw.value),
    parseFloat(yaw.value), parseFloat(pitch.value));
  for (const input of inputs) input.oninput = send;
  element("button", { textContent: "Reset edits", onclick: () => { for (const i of inputs) i.value = 0; send(); } }, panel);
}
