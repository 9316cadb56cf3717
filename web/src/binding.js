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
    // R = [a0 | a1 | a2] -> unit quaternion x y z w, w >= 0 (Shepperd's method, the trace branch first: R is
    // orthonormal, so the result is unit to rounding; inline, as a call here cost two thirds of the loop)
    const trace = ax + ny + bz;
    let w, x, y, z, t;
    if (trace > 0) {
      t = 0.5 / Math.sqrt(trace + 1);
      w = 0.25 / t; x = (nz - by) * t; y = (bx - az) * t; z = (ay - nx) * t;
    } else if (ax > ny && ax > bz) {
      t = 0.5 / Math.sqrt(1 + ax - ny - bz);
      w = (nz - by) * t; x = 0.25 / t; y = (nx + ay) * t; z = (bx + az) * t;
    } else if (ny > bz) {
      t = 0.5 / Math.sqrt(1 + ny - ax - bz);
      w = (bx - az) * t; x = (nx + ay) * t; y = 0.25 / t; z = (by + nz) * t;
    } else {
      t = 0.5 / Math.sqrt(1 + bz - ax - ny);
      w = (ay - nx) * t; x = (bx + az) * t; y = (by + nz) * t; z = 0.25 / t;
    }
    const sign = w < 0 ? -1 : 1;
    out[o + 4] = x * sign; out[o + 5] = y * sign; out[o + 6] = z * sign; out[o + 7] = w * sign;
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
