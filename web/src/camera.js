// Cameras of the player: the dataset camera (OpenCV world-to-camera + intrinsics, as render/camera.py) as a
// three.js camera, and the orbit about the head (render/camera.py orbit_viewmat: positive yaw moves the camera
// toward its right, positive pitch up).
import * as THREE from "three";

const NEAR = 0.01;
const FAR = 100.0;

// Projection of pinhole intrinsics (pixel centres at +0.5, as the CPU renderer) for an image width x height.
export function projectionFromIntrinsics(K, width, height, near = NEAR, far = FAR) {
  const [fx, cx, fy, cy] = [K[0][0], K[0][2], K[1][1], K[1][2]];
  const m = new THREE.Matrix4();
  m.set(
    (2 * fx) / width, 0, 1 - (2 * cx) / width, 0,
    0, (2 * fy) / height, (2 * cy) / height - 1, 0,
    0, 0, -(far + near) / (far - near), (-2 * far * near) / (far - near),
    0, 0, -1, 0,
  );
  return m;
}

// Camera-to-world of a three.js camera (OpenGL axes) from an OpenCV world-to-camera matrix (rows).
export function worldFromViewmat(viewmat) {
  const w2c = new THREE.Matrix4().set(...viewmat.flat());
  const flip = new THREE.Matrix4().makeScale(1, -1, -1); // OpenCV (+y down, +z forward) -> OpenGL
  return w2c.invert().multiply(flip);
}

// Point `camera` with world matrix `c2w` and projection `projection`.
export function placeCamera(camera, c2w, projection) {
  c2w.decompose(camera.position, camera.quaternion, camera.scale);
  camera.updateMatrixWorld(true);
  camera.projectionMatrix.copy(projection);
  camera.projectionMatrixInverse.copy(projection).invert();
}

// The dataset camera turned about `centre` by yaw / pitch (degrees), aimed at it, `distanceScale` x as far.
export function orbitWorld(viewmat, centre, yawDeg, pitchDeg, distanceScale = 1.0) {
  const base = worldFromViewmat(viewmat); // OpenGL axes: +x right, +y up
  const right = new THREE.Vector3().setFromMatrixColumn(base, 0);
  const up = new THREE.Vector3().setFromMatrixColumn(base, 1);
  const eye = new THREE.Vector3().setFromMatrixPosition(base);
  const c = new THREE.Vector3(...centre);
  const turn = new THREE.Matrix4()
    .makeRotationAxis(up, THREE.MathUtils.degToRad(yawDeg))
    .multiply(new THREE.Matrix4().makeRotationAxis(right, THREE.MathUtils.degToRad(-pitchDeg)));
  const offset = eye.sub(c).applyMatrix4(turn).multiplyScalar(distanceScale);
  const position = c.clone().add(offset);
  const turnedUp = up.applyMatrix4(turn);
  const look = new THREE.Matrix4().lookAt(position, c, turnedUp); // rotation with -z toward the centre
  return look.setPosition(position);
}

// The dataset intrinsics for a view of another size: the focal scaled to the height, the principal point centred.
export function fittedIntrinsics(K, height, viewWidth, viewHeight) {
  const s = viewHeight / height;
  return [
    [K[0][0] * s, 0, viewWidth / 2],
    [0, K[1][1] * s, viewHeight / 2],
    [0, 0, 1],
  ];
}

export function clamp(value, [lo, hi]) {
  return Math.min(hi, Math.max(lo, value));
}
