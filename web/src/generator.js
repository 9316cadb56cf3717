// The avatar as a Spark splat generator: every splat is placed, rotated, scaled and shaded on the GPU from
// two float textures, the avatar's local Gaussians (uploaded once) and the face frames (uploaded per frame).
import * as THREE from "three";
import { SplatGenerator, dyno } from "@sparkjsdev/spark";

export const TEXTURE_WIDTH = 2048; // texels per row of both textures (a linear index i is texel (i & 2047, i >> 11))
export const SPLAT_TEXELS = 6; // RGBA texels per splat in the avatar table (see geoavatar/web/pack.py)
export const FACE_TEXELS = 2; // RGBA texels per face: C, k | q (binding.js FACE_STRIDE)

// A float RGBA texture holding `texels` texels of `data` (padded to whole rows).
export function floatTexture(texels) {
  const rows = Math.max(1, Math.ceil(texels / TEXTURE_WIDTH));
  const data = new Float32Array(rows * TEXTURE_WIDTH * 4);
  const texture = new THREE.DataTexture(data, TEXTURE_WIDTH, rows, THREE.RGBAFormat, THREE.FloatType);
  texture.internalFormat = "RGBA32F";
  texture.minFilter = texture.magFilter = THREE.NearestFilter;
  texture.generateMipmaps = false;
  texture.needsUpdate = true;
  return texture;
}

// Table rows per splat (float32 x 24), written by geoavatar/web/pack.py:
//   t0 local mean (face-scale units) xyz, face index | t1 local rotation x y z w (unit) |
//   t2 local scale (linear) xyz, opacity | t3 colour rgb (SH-0), F[2][2] | t4 F[0][0..2], F[1][0] | t5 F[1][1..2], F[2][0..1]
// F: the normal-shading matrix (colour += F n, n the world face normal); zeros when the avatar has none.
const PLACE_GLSL = `
ivec2 gaTexel(int i) { return ivec2(i & ${TEXTURE_WIDTH - 1}, i >> ${Math.log2(TEXTURE_WIDTH)}); }
void gaPlaceSplat(sampler2D table, sampler2D faces, int index, bool shading, out Gsplat g) {
  int base = ${SPLAT_TEXELS} * index;
  vec4 t0 = texelFetch(table, gaTexel(base), 0);
  vec4 t1 = texelFetch(table, gaTexel(base + 1), 0);
  vec4 t2 = texelFetch(table, gaTexel(base + 2), 0);
  vec4 t3 = texelFetch(table, gaTexel(base + 3), 0);
  int face = int(t0.w + 0.5);
  vec4 centreScale = texelFetch(faces, gaTexel(${FACE_TEXELS} * face), 0);
  vec4 faceQuat = texelFetch(faces, gaTexel(${FACE_TEXELS} * face + 1), 0);
  g.center = centreScale.w * quatVec(faceQuat, t0.xyz) + centreScale.xyz;
  g.quaternion = quatQuat(faceQuat, t1);
  g.scales = centreScale.w * t2.xyz;
  vec3 colour = t3.rgb;
  if (shading) {
    vec4 t4 = texelFetch(table, gaTexel(base + 4), 0);
    vec4 t5 = texelFetch(table, gaTexel(base + 5), 0);
    vec3 normal = quatVec(faceQuat, vec3(0.0, 1.0, 0.0));
    colour += vec3(dot(t4.xyz, normal), dot(vec3(t4.w, t5.xy), normal), dot(vec3(t5.zw, t3.w), normal));
  }
  g.rgba = vec4(max(colour, vec3(0.0)), t2.w);
  g.index = index;
  g.flags = GSPLAT_FLAG_ACTIVE;
}
`;

// A SplatGenerator of `count` splats; call .updateVersion() after the face texture changed.
export function avatarGenerator({ count, table, faces, shading }) {
  const tableUniform = dyno.dynoSampler2D(table, "gaTable");
  const faceUniform = dyno.dynoSampler2D(faces, "gaFaces");
  const shadingUniform = dyno.dynoBool(Boolean(shading));
  const generator = dyno.dynoBlock({ index: "int" }, { gsplat: dyno.Gsplat }, ({ index }) => {
    const placed = dyno.dyno({
      inTypes: { index: "int", table: "sampler2D", faces: "sampler2D", shading: "bool" },
      outTypes: { gsplat: dyno.Gsplat },
      inputs: { index, table: tableUniform, faces: faceUniform, shading: shadingUniform },
      globals: () => [dyno.defineGsplat, PLACE_GLSL],
      statements: ({ inputs, outputs }) => [
        `gaPlaceSplat(${inputs.table}, ${inputs.faces}, ${inputs.index}, ${inputs.shading}, ${outputs.gsplat});`,
      ],
    });
    return { gsplat: placed.outputs.gsplat };
  });
  return new SplatGenerator({ numSplats: count, generator });
}
