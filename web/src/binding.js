// Face frames of a posed mesh and clip dequantisation: the maths of geoavatar/avatar/binding.py in plain JS.
//
// Per face (v0, v1, v2):
//   a0 = normalize(v1 - v0); a1 = normalize(a0 x (v2 - v0)) (the normal); a2 = a0 x a1 (= -normalize(a1 x a0))
//   R = [a0 | a1 | a2] (columns); C = (v0 + v1 + v2) / 3; k = (|v1 - v0| + |a2 . (v2 - v0)|) / 2
// The GPU places each splat with the face's (C, k, q(R)): mu_g = k R mu + C, q_g = q(R) (x) q, s_g = k s.
// tests/test_web_binding.py checks these numbers against binding.face_frames on the same vertices.

export const FACE_STRIDE = 8; // floats per face: C.x C.y C.z k | q.x q.y q.z q.w (two RGBA texels)
const EPS = 1e-12; // binding.py's floor under squared norms

function invNorm(x, y, z) {
  return 1 / Math.sqrt(Math.max(x * x + y * y + z * z, EPS));
}

// Rotation matrix (columns a0, a1, a2) -> unit quaternion written as x, y, z, w at out[o..o+3], w >= 0
// (Shepperd's method, the best-conditioned of the four candidates, as geometry.matrix_to_quaternion).
function writeQuaternion(m00, m01, m02, m10, m11, m12, m20, m21, m22, out, o) {
  const tw = 1 + m00 + m11 + m22;
  const tx = 1 + m00 - m11 - m22;
  const ty = 1 - m00 + m11 - m22;
  const tz = 1 - m00 - m11 + m22;
  let w, x, y, z;
  if (tw >= tx && tw >= ty && tw >= tz) {
    const s = 2 * Math.sqrt(Math.max(tw, EPS));
    w = s / 4; x = (m21 - m12) / s; y = (m02 - m20) / s; z = (m10 - m01) / s;
  } else if (tx >= ty && tx >= tz) {
    const s = 2 * Math.sqrt(Math.max(tx, EPS));
    w = (m21 - m12) / s; x = s / 4; y = (m10 + m01) / s; z = (m02 + m20) / s;
  } else if (ty >= tz) {
    const s = 2 * Math.sqrt(Math.max(ty, EPS));
    w = (m02 - m20) / s; x = (m10 + m01) / s; y = s / 4; z = (m21 + m12) / s;
  } else {
    const s = 2 * Math.sqrt(Math.max(tz, EPS));
    w = (m10 - m01) / s; x = (m20 + m02) / s; y = (m21 + m12) / s; z = s / 4;
  }
  const n = (w < 0 ? -1 : 1) / Math.sqrt(w * w + x * x + y * y + z * z);
  out[o] = x * n; out[o + 1] = y * n; out[o + 2] = z * n; out[o + 3] = w * n;
}

// vertices: Float32Array [V * 3]; faces: Uint32Array [F * 3]; out: Float32Array [F * FACE_STRIDE] (returned).
export function faceFrames(vertices, faces, out) {
  const count = faces.length / 3;
  out = out ?? new Float32Array(count * FACE_STRIDE);
  for (let f = 0; f < count; f++) {
    const i0 = 3 * faces[3 * f], i1 = 3 * faces[3 * f + 1], i2 = 3 * faces[3 * f + 2];
    const x0 = vertices[i0], y0 = vertices[i0 + 1], z0 = vertices[i0 + 2];
    const e0x = vertices[i1] - x0, e0y = vertices[i1 + 1] - y0, e0z = vertices[i1 + 2] - z0;
    const e2x = vertices[i2] - x0, e2y = vertices[i2 + 1] - y0, e2z = vertices[i2 + 2] - z0;
    let s = invNorm(e0x, e0y, e0z);
    const ax = e0x * s, ay = e0y * s, az = e0z * s; // a0
    let nx = ay * e2z - az * e2y, ny = az * e2x - ax * e2z, nz = ax * e2y - ay * e2x;
    s = invNorm(nx, ny, nz);
    nx *= s; ny *= s; nz *= s; // a1, the normal
    let bx = ay * nz - az * ny, by = az * nx - ax * nz, bz = ax * ny - ay * nx; // a0 x a1
    s = invNorm(bx, by, bz);
    bx *= s; by *= s; bz *= s; // a2
    const o = FACE_STRIDE * f;
    out[o] = x0 + (e0x + e2x) / 3;
    out[o + 1] = y0 + (e0y + e2y) / 3;
    out[o + 2] = z0 + (e0z + e2z) / 3;
    const base = Math.sqrt(Math.max(e0x * e0x + e0y * e0y + e0z * e0z, EPS));
    out[o + 3] = (base + Math.abs(bx * e2x + by * e2y + bz * e2z)) / 2;
    // rows of R = [a0 | a1 | a2]: R[i][j] = column j, component i
    writeQuaternion(ax, nx, bx, ay, ny, by, az, nz, bz, out, o + 4);
  }
  return out;
}

// One frame of a quantised clip: uint16 [T, V, 3] -> Float32Array [V * 3], v = offset + q * step per axis.
export function dequantiseFrame(clip, frame, vertexCount, offset, step, out) {
  const n = vertexCount * 3;
  out = out ?? new Float32Array(n);
  const start = frame * n;
  for (let i = 0; i < n; i += 3) {
    out[i] = offset[0] + clip[start + i] * step[0];
    out[i + 1] = offset[1] + clip[start + i + 1] * step[1];
    out[i + 2] = offset[2] + clip[start + i + 2] * step[2];
  }
  return out;
}
