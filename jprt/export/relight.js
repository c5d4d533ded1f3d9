// Relighting a jprt export in three.js on the GPU, from the lighting jprt's evaluator takes.
//
//   import { relightMaterial } from "./relight.js";
//   const relight = await relightMaterial("exports/sh_prt/");    // the export folder's URL
//   relight.setLighting({ coefficients: [[r, g, b], ...] });     // SH PRT: an SHLighting
//   relight.setLighting({ direct: [[r, g, b], ...] });           // data-driven PRT: a PointRadiance
//   mesh.material = relight.material;                            // meshes of scene.glb (uv1 = TEXCOORD_1)
//
// The material outputs the indirect radiance (W m^-2 sr^-1, linear RGB) that jprt's evaluator
// predicts, without tone mapping: render it to a float target to read the numbers back.
//   * SH PRT (Sloan et al. 2002 Eq. 5): radiance = sum_i t_i l_i, the transfer vectors t_i of
//     params/transfer.bin as the layers of a float texture array, the coefficients l_i uniforms.
//   * data-driven PRT (Belcour et al. 2022 §4.3, basis.channels "mono", no gamma): the direct
//     radiance at the fine measurement points is averaged per coarse point (params/group.bin,
//     params/counts.bin) into x, u = M x per channel (params/transfer.bin) on the CPU (a small
//     matrix-vector product), and the shader sums mean |x| + sum_i b_i u_i over the basis layers.
// Textures are filled through the atlas's fill_index (gutters repeat their nearest texel) and read
// with bilinear filtering, texel centres at (i + 0.5) / R, as jprt's atlas lookup reads them.
import * as THREE from "three";

async function json(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`cannot fetch ${url}: ${response.status}`);
  return response.json();
}

async function buffer(base, manifest, key) {
  const entry = manifest.params.find((e) => e.keys.length === 1 && e.keys[0] === key);
  if (!entry) throw new Error(`the export has no params/${key}.bin`);
  const response = await fetch(base + entry.file);
  if (!response.ok) throw new Error(`cannot fetch ${entry.file}: ${response.status}`);
  const bytes = await response.arrayBuffer();
  const Type = { float32: Float32Array, int32: Int32Array, uint32: Uint32Array }[entry.dtype];
  if (!Type) throw new Error(`params/${key}.bin is ${entry.dtype}; relight.js reads float32 and int32`);
  return { data: new Type(bytes), shape: entry.shape };
}

// layers[k](texel) -> [r, g, b] for every texel; returns an RGBA float texture array (R, R, K).
function layerTexture(fill, resolution, count, texelValue) {
  const data = new Float32Array(resolution * resolution * count * 4);
  for (let k = 0; k < count; k++) {
    for (let p = 0; p < resolution * resolution; p++) {
      const v = texelValue(k, fill[p]);
      const o = (k * resolution * resolution + p) * 4;
      data[o] = v[0]; data[o + 1] = v[1]; data[o + 2] = v[2]; data[o + 3] = 1.0;
    }
  }
  const texture = new THREE.DataArrayTexture(data, resolution, resolution, count);
  texture.format = THREE.RGBAFormat;
  texture.type = THREE.FloatType;
  texture.magFilter = texture.minFilter = THREE.LinearFilter;
  texture.wrapS = texture.wrapT = THREE.ClampToEdgeWrapping;
  texture.generateMipmaps = false;
  texture.needsUpdate = true;
  return texture;
}

function layerMaterial(texture, count) {
  return new THREE.ShaderMaterial({
    glslVersion: THREE.GLSL3,
    side: THREE.DoubleSide,
    defines: { LAYERS: count },
    uniforms: { layers: { value: texture }, weights: { value: Array.from({ length: count }, () => new THREE.Vector3()) } },
    vertexShader: `
      in vec2 uv1;
      out vec2 vLightmapUv;
      void main() {
        vLightmapUv = uv1;
        gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
      }`,
    fragmentShader: `
      precision highp float;
      precision highp sampler2DArray;
      uniform sampler2DArray layers;
      uniform vec3 weights[LAYERS];
      in vec2 vLightmapUv;
      out vec4 radiance;
      void main() {
        vec3 sum = vec3(0.0);
        for (int k = 0; k < LAYERS; k++) sum += texture(layers, vec3(vLightmapUv, float(k))).rgb * weights[k];
        radiance = vec4(sum, 1.0);
      }`,
  });
}

async function shPrt(base, manifest) {
  const transfer = await buffer(base, manifest, "transfer");  // (T, n, 3)
  const fill = (await buffer(base, manifest, "fill_index")).data;
  const [, n] = transfer.shape;
  const res = manifest.lightmap.resolution;
  const t = transfer.data;
  const texture = layerTexture(fill, res, n, (k, texel) => [0, 1, 2].map((c) => t[(texel * n + k) * 3 + c]));
  const material = layerMaterial(texture, n);
  return {
    material,
    setLighting({ coefficients }) {
      if (coefficients.length > n) throw new Error(`${coefficients.length} SH coefficients, the transfer holds ${n}`);
      material.uniforms.weights.value.forEach((w, k) => w.fromArray(coefficients[k] || [0, 0, 0]));
    },
  };
}

async function dataDriven(base, manifest) {
  const basisCfg = manifest.config.basis;
  if (basisCfg.channels !== "mono" || basisCfg.gamma > 0)
    throw new Error(`relight.js relights data-driven PRT with basis.channels "mono" and no gamma, this export has ` +
                    `${basisCfg.channels} and gamma ${basisCfg.gamma}`);
  const basis = await buffer(base, manifest, "basis");  // (T, n)
  const mean = (await buffer(base, manifest, "mean")).data;  // (T,)
  const transfer = await buffer(base, manifest, "transfer");  // (3, n, P)
  const group = (await buffer(base, manifest, "group")).data;  // (S,)
  const counts = (await buffer(base, manifest, "counts")).data;  // (P,)
  const fill = (await buffer(base, manifest, "fill_index")).data;
  const [, n] = basis.shape;
  const p = counts.length;
  const res = manifest.lightmap.resolution;
  const b = basis.data;
  // layer 0: the mean (weighted by |x|), layers 1..n: the basis vectors (weighted by u)
  const texture = layerTexture(fill, res, n + 1, (k, texel) => {
    const v = k === 0 ? mean[texel] : b[texel * n + k - 1];
    return [v, v, v];
  });
  const material = layerMaterial(texture, n + 1);
  return {
    material,
    setLighting({ direct }) {
      if (direct.length !== group.length)
        throw new Error(`direct radiance at ${direct.length} points, the model measures ${group.length}`);
      const x = Array.from({ length: p }, () => [0, 0, 0]);
      direct.forEach((d, s) => { for (let c = 0; c < 3; c++) x[group[s]][c] += d[c] / counts[group[s]]; });
      const norm = [0, 1, 2].map((c) => Math.sqrt(x.reduce((acc, v) => acc + v[c] * v[c], 0)));
      material.uniforms.weights.value[0].fromArray(norm);
      for (let i = 0; i < n; i++) {
        const u = [0, 1, 2].map((c) => {
          let acc = 0;
          for (let q = 0; q < p; q++) acc += transfer.data[(c * n + i) * p + q] * x[q][c];
          return acc;
        });
        material.uniforms.weights.value[i + 1].fromArray(u);
      }
    },
  };
}

// The relighting material of the export at `base` (its URL, ending in "/"): {material, setLighting}.
export async function relightMaterial(base) {
  const manifest = await json(base + "export.json");
  if (manifest.method === "sh_prt") return shPrt(base, manifest);
  if (manifest.method === "datadriven") return dataDriven(base, manifest);
  throw new Error(`relight.js relights SH PRT and data-driven PRT exports, not ${manifest.method}`);
}
