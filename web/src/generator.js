// The avatar as a Spark splat generator: every splat is placed, rotated, scaled and shaded on the GPU from
// float textures: the avatar's local Gaussians (anchors and rows, uploaded once) and the face frames (per frame).
import * as THREE from "three";
import { SplatGenerator, dyno } from "@sparkjsdev/spark";

export const TEXTURE_WIDTH = 2048; // texels per row of every texture (a linear index i is texel (i & 2047, i >> 11))
export const ROW_TEXELS = 5; // RGBA16F texels per splat in the row table; its anchor is one RGBA32F texel (pack.py)
export const FACE_TEXELS = 2; // RGBA texels per face: C, k | q (binding.js FACE_STRIDE)
export const POSE_TEXELS = 9; // RGBA16F texels per moving splat in the pose table (hair that follows the head)

// An RGBA texture of `texels` texels (padded to whole rows), nearest sampling, its data zeroed: float32 or half.
function rgbaTexture(texels, ArrayType, type, internalFormat) {
  const rows = Math.max(1, Math.ceil(texels / TEXTURE_WIDTH));
  const texture = new THREE.DataTexture(new ArrayType(rows * TEXTURE_WIDTH * 4), TEXTURE_WIDTH, rows, THREE.RGBAFormat,
    type);
  texture.internalFormat = internalFormat;
  texture.minFilter = texture.magFilter = THREE.NearestFilter;
  texture.generateMipmaps = false;
  texture.needsUpdate = true;
  return texture;
}

export const floatTexture = (texels) => rgbaTexture(texels, Float32Array, THREE.FloatType, "RGBA32F");
// uint16 IEEE halves (the row and pose tables: numpy float16)
export const halfTexture = (texels) => rgbaTexture(texels, Uint16Array, THREE.HalfFloatType, "RGBA16F");

// Per splat, written by geoavatar/web/pack.py: the anchor (float32) t0 local mean (face-scale units) xyz, face index;
// the row (float16) t1 local rotation x y z w (unit) | t2 local scale (linear) xyz, opacity |
// t3 colour rgb (SH-0), F[2][2] | t4 F[0][0..2], F[1][0] | t5 F[1][1..2], F[2][0..1]
// F: the normal-shading matrix (colour += F n, n the world face normal); zeros when the avatar has none.
// Pose rows (float16 x 36, only when the hair follows the head, for the first `posed` splats: the export puts the
// moving ones first): M [3][6] then C [3][6] row-major; with the frame's head pose code c = (head rotation, neck)
// the local mean takes M c and the colour C c (avatar/model.py).
const PLACE_GLSL = `
ivec2 gaTexel(int i) { return ivec2(i & ${TEXTURE_WIDTH - 1}, i >> ${Math.log2(TEXTURE_WIDTH)}); }
// A row of six weights applied to the code (head, neck): starting at a texel's x (aligned) or at its z (mid).
float gaRowAligned(vec4 a, vec4 b, vec3 head, vec3 neck) { return dot(a.xyz, head) + dot(vec3(a.w, b.xy), neck); }
float gaRowMid(vec4 a, vec4 b, vec3 head, vec3 neck) { return dot(vec3(a.zw, b.x), head) + dot(b.yzw, neck); }
void gaPlaceSplat(sampler2D anchors, sampler2D rows, sampler2D faces, sampler2D poses, int index, bool shading,
                  int posed, vec3 head, vec3 neck, out Gsplat g) {
  int base = ${ROW_TEXELS} * index;
  vec4 t0 = texelFetch(anchors, gaTexel(index), 0);
  vec4 t1 = texelFetch(rows, gaTexel(base), 0);
  vec4 t2 = texelFetch(rows, gaTexel(base + 1), 0);
  vec4 t3 = texelFetch(rows, gaTexel(base + 2), 0);
  vec3 localMean = t0.xyz;
  vec3 colour = t3.rgb;
  if (index < posed) {
    int row = ${POSE_TEXELS} * index;
    vec4 p0 = texelFetch(poses, gaTexel(row), 0), p1 = texelFetch(poses, gaTexel(row + 1), 0);
    vec4 p2 = texelFetch(poses, gaTexel(row + 2), 0), p3 = texelFetch(poses, gaTexel(row + 3), 0);
    vec4 p4 = texelFetch(poses, gaTexel(row + 4), 0), p5 = texelFetch(poses, gaTexel(row + 5), 0);
    vec4 p6 = texelFetch(poses, gaTexel(row + 6), 0), p7 = texelFetch(poses, gaTexel(row + 7), 0);
    vec4 p8 = texelFetch(poses, gaTexel(row + 8), 0);
    localMean += vec3(gaRowAligned(p0, p1, head, neck), gaRowMid(p1, p2, head, neck), gaRowAligned(p3, p4, head, neck));
    colour += vec3(gaRowMid(p4, p5, head, neck), gaRowAligned(p6, p7, head, neck), gaRowMid(p7, p8, head, neck));
  }
  int face = int(t0.w + 0.5);
  vec4 centreScale = texelFetch(faces, gaTexel(${FACE_TEXELS} * face), 0);
  vec4 faceQuat = texelFetch(faces, gaTexel(${FACE_TEXELS} * face + 1), 0);
  g.center = centreScale.w * quatVec(faceQuat, localMean) + centreScale.xyz;
  g.quaternion = quatQuat(faceQuat, t1);
  g.scales = centreScale.w * t2.xyz;
  if (shading) {
    vec4 t4 = texelFetch(rows, gaTexel(base + 3), 0);
    vec4 t5 = texelFetch(rows, gaTexel(base + 4), 0);
    vec3 normal = quatVec(faceQuat, vec3(0.0, 1.0, 0.0));
    colour += vec3(dot(t4.xyz, normal), dot(vec3(t4.w, t5.xy), normal), dot(vec3(t5.zw, t3.w), normal));
  }
  g.rgba = vec4(max(colour, vec3(0.0)), t2.w);
  g.index = index;
  g.flags = GSPLAT_FLAG_ACTIVE;
}
`;

// A SplatGenerator of `count` splats; call .updateVersion() after the face texture or the pose code changed.
// anchors: float texture, rows: half-float texture (pack.py); poses: the pose table's half-float texture of the
// first `posed` splats when the hair follows the head (null: it does not); the returned generator's
// setPoseCode(code) takes the frame's head pose code [6].
export function avatarGenerator({ count, anchors, rows, faces, shading, poses, posed }) {
  const anchorUniform = dyno.dynoSampler2D(anchors, "gaAnchors");
  const rowUniform = dyno.dynoSampler2D(rows, "gaRows");
  const faceUniform = dyno.dynoSampler2D(faces, "gaFaces");
  const poseUniform = dyno.dynoSampler2D(poses ?? halfTexture(1), "gaPoses");
  const shadingUniform = dyno.dynoBool(Boolean(shading));
  const posedUniform = dyno.dynoInt(poses ? posed : 0);
  const headUniform = dyno.dynoVec3(new THREE.Vector3(), "gaHead");
  const neckUniform = dyno.dynoVec3(new THREE.Vector3(), "gaNeck");
  const generator = dyno.dynoBlock({ index: "int" }, { gsplat: dyno.Gsplat }, ({ index }) => {
    const placed = dyno.dyno({
      inTypes: { index: "int", anchors: "sampler2D", rows: "sampler2D", faces: "sampler2D", poses: "sampler2D",
        shading: "bool", posed: "int", head: "vec3", neck: "vec3" },
      outTypes: { gsplat: dyno.Gsplat },
      inputs: { index, anchors: anchorUniform, rows: rowUniform, faces: faceUniform, poses: poseUniform,
        shading: shadingUniform, posed: posedUniform, head: headUniform, neck: neckUniform },
      globals: () => [dyno.defineGsplat, PLACE_GLSL],
      statements: ({ inputs: i, outputs }) => [
        `gaPlaceSplat(${i.anchors}, ${i.rows}, ${i.faces}, ${i.poses}, ${i.index}, ${i.shading}, ${i.posed}, ` +
        `${i.head}, ${i.neck}, ${outputs.gsplat});`,
      ],
    });
    return { gsplat: placed.outputs.gsplat };
  });
  const splats = new SplatGenerator({ numSplats: count, generator });
  splats.setPoseCode = (code) => {
    headUniform.value.set(code[0], code[1], code[2]);
    neckUniform.value.set(code[3], code[4], code[5]);
  };
  return splats;
}
