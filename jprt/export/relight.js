// Relighting a jprt export in three.js on the GPU, from the lighting jprt's evaluator takes.
//
//   import { relightMaterial } from "./relight.js";
//   const relight = await relightMaterial("exports/sh_prt/");    // the export folder's URL
//   relight.setLighting({ coefficients: [[r, g, b], ...] });     // SH PRT: an SHLighting
//   relight.setLighting({ direct: [[r, g, b], ...] });           // data-driven PRT, MRT: a PointRadiance
//   relight.setLighting({ scale: [r, g, b] });                   // SG light-field textures: a LightScale
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
//   * SG light-field textures (Currius et al. 2020): the shader fetches the texel's lobes
//     (params/axes, sharpness, amplitude: float16), its irradiance and its material
//     (sg_materials.bin), shades the lobes as the export's config says (shading.samples,
//     brdf_sampling, broad_bound): by samples^2 directions drawn from each lobe through the GGX
//     BRDF (jprt's shade_sampled; a lobe broader than the BRDF at samples^2 directions drawn from
//     the BRDF's visible normals, where brdf_sampling is on), or, at
//     0 or in exports without the key, by Appendix B (Eq. 15-24: the GGX NDF warped to an ASG about
//     the reflected view direction, convolved with each lobe by Xu et al. 2013 Eq. 12, Smith G,
//     Schlick's Fresnel and n.l at that direction); adds albedo / pi x irradiance and scales by the
//     LightScale; view = the camera's direction. Every fragment shades its own filtered lobes:
//     jprt's shading.space "pixel" (§6), not the texture-space shading its evaluator uses where
//     the atlas has fewer texels than the frame has pixels.
//   * MRT (Loos et al. 2011 §7.3): b = T_d->b x per block, the interface records r = T_b->r b, the
//     feedback bounces in the reduced spaces (W, V), then the incident light U_b b + U_r r at every
//     texel: on the CPU (operators of a few hundred numbers per block); the shader multiplies the
//     texel albedo by the bilinear incident-light lightmap.
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
  if (entry.dtype === "float16") return { data: halfToFloat(new Uint16Array(bytes)), shape: entry.shape };
  const Type = { float32: Float32Array, int32: Int32Array, uint32: Uint32Array, bool: Uint8Array }[entry.dtype];
  if (!Type) throw new Error(`params/${key}.bin is ${entry.dtype}; relight.js reads float16, float32, int32 and bool`);
  return { data: new Type(bytes), shape: entry.shape };
}

// IEEE half-precision bit patterns -> Float32Array (exact: every float16 is a float32)
function halfToFloat(bits) {
  const out = new Float32Array(bits.length);
  for (let i = 0; i < bits.length; i++) {
    const h = bits[i], sign = h & 0x8000 ? -1 : 1, exp = (h >> 10) & 0x1f, frac = h & 0x3ff;
    out[i] = exp === 0 ? sign * frac * 2 ** -24
      : exp === 31 ? (frac ? NaN : sign * Infinity)
      : sign * (1 + frac / 1024) * 2 ** (exp - 15);
  }
  return out;
}

async function rawFloats(base, manifest, file) {
  if (!manifest.files[file]) throw new Error(`the export has no ${file}`);
  const response = await fetch(base + file);
  if (!response.ok) throw new Error(`cannot fetch ${file}: ${response.status}`);
  return new Float32Array(await response.arrayBuffer());
}

// layers[k](texel) -> [r, g, b(, a)] for every texel; returns an RGBA float texture array (R, R, K).
function layerTexture(fill, resolution, count, texelValue) {
  const data = new Float32Array(resolution * resolution * count * 4);
  for (let k = 0; k < count; k++) {
    for (let p = 0; p < resolution * resolution; p++) {
      const v = texelValue(k, fill[p]);
      const o = (k * resolution * resolution + p) * 4;
      data[o] = v[0]; data[o + 1] = v[1]; data[o + 2] = v[2]; data[o + 3] = v.length > 3 ? v[3] : 1.0;
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

// the meshes' vertex stage: the lightmap UV (TEXCOORD_1) passed on
const VERTEX_UV = `
  in vec2 uv1;
  out vec2 vLightmapUv;
  void main() {
    vLightmapUv = uv1;
    gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
  }`;

function layerMaterial(texture, count) {
  return new THREE.ShaderMaterial({
    glslVersion: THREE.GLSL3,
    side: THREE.DoubleSide,
    defines: { LAYERS: count },
    uniforms: { layers: { value: texture }, weights: { value: Array.from({ length: count }, () => new THREE.Vector3()) } },
    vertexShader: VERTEX_UV,
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
  // a demodulated fit's basis holds the texels' light over their texture: put it back per channel
  const modulation = manifest.params.some((e) => e.keys.length === 1 && e.keys[0] === "texel_modulation")
    ? (await buffer(base, manifest, "texel_modulation")).data : null;  // (T, 3)
  const [, n] = basis.shape;
  const p = counts.length;
  const res = manifest.lightmap.resolution;
  const b = basis.data;
  // layer 0: the mean (weighted by |x|), layers 1..n: the basis vectors (weighted by u)
  const texture = layerTexture(fill, res, n + 1, (k, texel) => {
    const v = k === 0 ? mean[texel] : b[texel * n + k - 1];
    return modulation ? [0, 1, 2].map((c) => v * modulation[texel * 3 + c]) : [v, v, v];
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

const VERTEX_WORLD = `
  in vec2 uv1;
  out vec2 vLightmapUv;
  out vec3 vWorld;
  out vec3 vNormal;
  void main() {
    vLightmapUv = uv1;
    vec4 world = modelMatrix * vec4(position, 1.0);
    vWorld = world.xyz;
    vNormal = normalize(mat3(modelMatrix) * normal);
    gl_Position = projectionMatrix * viewMatrix * world;
  }`;

async function sgLightfield(base, manifest) {
  const axes = (await buffer(base, manifest, "axes")).data;  // (T, N, 3)
  const sharpness = await buffer(base, manifest, "sharpness");  // (T, N)
  const amplitude = (await buffer(base, manifest, "amplitude")).data;  // (T, N, 3)
  const irradiance = (await buffer(base, manifest, "irradiance")).data;  // (T, 3)
  const fill = (await buffer(base, manifest, "fill_index")).data;
  const materials = await rawFloats(base, manifest, "sg_materials.bin");  // (T, 7)
  const [, n] = sharpness.shape;
  const res = manifest.lightmap.resolution;
  const samples = manifest.config?.shading?.samples ?? 0;  // 0: Appendix B's product
  // a lobe broader than the BRDF at the BRDF's directions (exports without the key: lobe-drawn only)
  const brdfSampling = manifest.config?.shading?.brdf_sampling ? 1 : 0;
  const broadBound = Number(manifest.config?.shading?.broad_bound ?? 1.0);
  const sh = sharpness.data;
  // layers 2j: lobe j's axis and sharpness, 2j + 1: its amplitude; 2N: irradiance;
  // 2N + 1: diffuse albedo and roughness; 2N + 2: specular reflectance at normal incidence
  const texture = layerTexture(fill, res, 2 * n + 3, (k, t) => {
    if (k < 2 * n) {
      const j = k >> 1, o = (t * n + j) * 3;
      return k % 2 === 0 ? [axes[o], axes[o + 1], axes[o + 2], sh[t * n + j]]
                         : [amplitude[o], amplitude[o + 1], amplitude[o + 2], 0];
    }
    if (k === 2 * n) return [irradiance[t * 3], irradiance[t * 3 + 1], irradiance[t * 3 + 2], 0];
    const m = t * 7;
    return k === 2 * n + 1 ? [materials[m], materials[m + 1], materials[m + 2], materials[m + 6]]
                           : [materials[m + 3], materials[m + 4], materials[m + 5], 0];
  });
  const material = new THREE.ShaderMaterial({
    glslVersion: THREE.GLSL3,
    side: THREE.DoubleSide,
    defines: { LOBES: n, SAMPLES: samples, BRDF_SAMPLING: brdfSampling, BROAD_BOUND: broadBound.toFixed(9) },
    uniforms: { lobes: { value: texture }, scale: { value: new THREE.Vector3(1, 1, 1) } },
    vertexShader: VERTEX_WORLD,
    fragmentShader: `
      precision highp float;
      precision highp sampler2DArray;
      uniform sampler2DArray lobes;
      uniform vec3 scale;
      in vec2 vLightmapUv;
      in vec3 vWorld;
      in vec3 vNormal;
      out vec4 radiance;
      vec4 at(int k) { return texture(lobes, vec3(vLightmapUv, float(k))); }
      // 1 / (n.x + sqrt(m2 + (1 - m2) n.x^2)) and n.x times it (the V = G / (4 n.l n.v) form)
      float ggxV1(float m2, float c) { return 1.0 / (c + sqrt(m2 + (1.0 - m2) * c * c)); }
      float ggxV1Cos(float m2, float c) { return c > 0.0 ? 1.0 / (1.0 + sqrt(1.0 - m2 + m2 / (c * c))) : 0.0; }
      void main() {
        vec3 v = normalize(cameraPosition - vWorld);
        vec3 nrm = normalize(vNormal);
        if (dot(nrm, v) < 0.0) nrm = -nrm;  // the G-buffer's normal faces the camera
        vec4 mat = at(2 * LOBES + 1);
        vec3 diffuse = mat.rgb, f0 = at(2 * LOBES + 2).rgb;
        float r = max(mat.a, 1e-3), r2 = r * r;
        float ndotv = dot(nrm, v), cosV = max(ndotv, 1e-4);
#if SAMPLES > 0
        // jprt's shade_sampled: SAMPLES^2 strata of each lobe (the SG's inverse CDF in 1 - cos, even
        // steps in phi), each an equal share of the lobe's integral through GGX D, separable Smith G
        // and Schlick's Fresnel, alpha^2 widened by 1 / (lambda SAMPLES^2) (a stratum's spread)
        const float S2 = float(SAMPLES * SAMPLES);
        vec3 plain = vec3(0.0), grazing = vec3(0.0);
#if BRDF_SAMPLING
        // jprt's _brdf_sampled: SAMPLES^2 directions drawn from the GGX visible normals (Heitz
        // 2018) at the view, shared by the lobes; each carries G1(l) (and Fresnel's grazing factor)
        // times a broad lobe's light there
        vec3 bl[SAMPLES * SAMPLES];
        float bw[SAMPLES * SAMPLES], bf[SAMPLES * SAMPLES];
        {
          float alpha = r, sgn = nrm.z >= 0.0 ? 1.0 : -1.0, fa = -1.0 / (sgn + nrm.z), fc = nrm.x * nrm.y * fa;
          vec3 tn = vec3(1.0 + sgn * nrm.x * nrm.x * fa, sgn * fc, -sgn * nrm.x);
          vec3 bn = vec3(fc, sgn + nrm.y * nrm.y * fa, -nrm.y);
          float vt = dot(v, tn), vb = dot(v, bn);
          vec3 st = vec3(alpha * vt, alpha * vb, cosV);
          st *= inversesqrt(dot(st, st));
          float lensq = st.x * st.x + st.y * st.y;
          bool far = lensq > 1e-12;
          float il = inversesqrt(far ? lensq : 1.0);
          vec2 t1 = far ? vec2(-st.y * il, st.x * il) : vec2(1.0, 0.0);
          vec3 t2 = vec3(-st.z * t1.y, st.z * t1.x, st.x * t1.y - st.y * t1.x);
          float half_ = 0.5 * (1.0 + st.z);
          for (int i = 0; i < SAMPLES; i++) {
            float rr = sqrt((float(i) + 0.5) / float(SAMPLES));
            for (int k = 0; k < SAMPLES; k++) {
              float phi = 6.283185307179586 * (float(k) + 0.5) / float(SAMPLES);
              float p1 = rr * cos(phi);
              float p2 = (1.0 - half_) * sqrt(max(1.0 - p1 * p1, 0.0)) + half_ * (rr * sin(phi));
              float p3 = sqrt(max(1.0 - p1 * p1 - p2 * p2, 0.0));
              vec3 m = vec3(p1 * t1.x + p2 * t2.x + p3 * st.x, p1 * t1.y + p2 * t2.y + p3 * st.y, p2 * t2.z + p3 * st.z);
              m = vec3(alpha * m.x, alpha * m.y, max(m.z, 0.0));
              m *= inversesqrt(max(dot(m, m), 1e-20));
              float vh = vt * m.x + vb * m.y + cosV * m.z;
              float nl = 2.0 * vh * m.z - cosV;
              vec3 h = m.x * tn + m.y * bn + m.z * nrm;
              vec3 l = 2.0 * vh * h - v;
              l *= inversesqrt(max(dot(l, l), 1e-20));
              float fw = 1.0 - clamp(vh, 0.0, 1.0);
              int q = i * SAMPLES + k;
              bl[q] = l;
              bw[q] = 2.0 * ggxV1Cos(r2, nl);
              bf[q] = fw * fw * fw * fw * fw;
            }
          }
        }
#endif
        for (int j = 0; j < LOBES; j++) {
          vec4 lobe = at(2 * j);
          vec3 amp = at(2 * j + 1).rgb;
          float lam = lobe.w;
          vec3 u = lobe.xyz * inversesqrt(max(dot(lobe.xyz, lobe.xyz), 1e-20));
#if BRDF_SAMPLING
          if (lam * 0.5 * r2 < BROAD_BOUND) {  // broader than the BRDF: its light at the BRDF's directions
            float bp = 0.0, bg = 0.0;
            for (int q = 0; q < SAMPLES * SAMPLES; q++) {
              vec3 dl = bl[q] - u;  // l . u - 1 = -|l - u|^2 / 2
              float light = exp(-0.5 * lam * dot(dl, dl)) * bw[q];
              bp += light;
              bg += light * bf[q];
            }
            plain += bp / S2 * amp;
            grazing += bg / S2 * amp;
            continue;
          }
#endif
          vec3 t = abs(u.z) >= 0.9 ? vec3(0.0, -u.z, u.y) : vec3(-u.y, u.x, 0.0);
          t *= inversesqrt(max(dot(t, t), 1e-20));
          vec3 b = cross(u, t);
          float a2 = r2 + 1.0 / (lam * S2), tail = 1.0 - exp(-2.0 * lam), gv = ggxV1(a2, cosV);
          float p = 0.0, g = 0.0;
          for (int i = 0; i < SAMPLES; i++) {
            float tt = -log(1.0 - (float(i) + 0.5) / float(SAMPLES) * tail) / lam;  // 1 - cos theta
            float cs = 1.0 - tt, sn = sqrt(max(tt * (2.0 - tt), 0.0));
            for (int k = 0; k < SAMPLES; k++) {
              float phi = 6.283185307179586 * (float(k) + 0.5) / float(SAMPLES);
              vec3 d = sn * cos(phi) * t + sn * sin(phi) * b + cs * u;
              vec3 h = d + v;
              h *= inversesqrt(max(dot(h, h), 1e-20));
              float c = dot(nrm, h), dd = a2 + max((1.0 - c) * (1.0 + c), 0.0) * (1.0 - a2);
              float value = c > 0.0 ? a2 / (3.14159265358979 * dd * dd) * ggxV1Cos(a2, dot(nrm, d)) * gv : 0.0;
              p += value;
              g += value * pow(1.0 - clamp(dot(d, h), 0.0, 1.0), 5.0);
            }
          }
          float e = 6.283185307179586 / S2 * tail / lam;
          plain += e * p * amp;
          grazing += e * g * amp;
        }
        vec3 glossy = f0 * plain + (1.0 - f0) * grazing;
#else
        // Eq. 18: the NDF warped to an ASG about z = reflect(-v, n); x across the plane of incidence
        vec3 z = 2.0 * ndotv * nrm - v;
        vec3 c = cross(nrm, z);
        vec3 x;
        if (dot(c, c) > 1e-6) x = c * inversesqrt(dot(c, c));
        else {  // normal incidence: the lobe is isotropic, any frame about z (Duff et al. 2017)
          float s = z.z >= 0.0 ? 1.0 : -1.0, a = -1.0 / (s + z.z), b = z.x * z.y * a;
          x = vec3(1.0 + s * z.x * z.x * a, s * b, -s * z.x);
        }
        vec3 y = cross(z, x);
        vec3 conv = vec3(0.0);
        for (int j = 0; j < LOBES; j++) {
          vec4 lobe = at(2 * j);
          vec3 axis = lobe.xyz * inversesqrt(max(dot(lobe.xyz, lobe.xyz), 1e-20));
          // Xu et al. 2013 Eq. 12 with the roughness cancelled (jprt's _warped_convolution)
          float nu = 0.5 * lobe.w, qx = 4.0 * nu * cosV * cosV * r2, qy = 4.0 * nu * r2;
          float sc = 4.0 * cosV * inversesqrt((1.0 + qx) * (1.0 + qy));
          float vx = dot(axis, x), vy = dot(axis, y), vz = dot(axis, z);
          float w = sc * max(vz, 0.0) * exp(-nu / (1.0 + qx) * vx * vx - nu / (1.0 + qy) * vy * vy);
          conv += w * at(2 * j + 1).rgb;
        }
        vec3 h = z + v;
        h *= inversesqrt(max(dot(h, h), 1e-20));
        float visCos = ggxV1Cos(r2, dot(nrm, z)) * ggxV1(r2, cosV);
        vec3 fresnel = f0 + (1.0 - f0) * pow(1.0 - clamp(dot(z, h), 0.0, 1.0), 5.0);
        vec3 glossy = conv * visCos * fresnel;
#endif
        radiance = vec4((glossy + diffuse / 3.14159265358979 * at(2 * LOBES).rgb) * scale, 1.0);
      }`,
  });
  return {
    material,
    setLighting({ scale }) {
      if (scale.length !== 3) throw new Error(`a LightScale has 3 channels, got ${scale.length}`);
      material.uniforms.scale.value.fromArray(scale);
    },
  };
}

async function mrt(base, manifest) {
  const get = async (key) => buffer(base, manifest, key);
  const tdb = await get("T_db");  // (B, kb, n)
  const ub = (await get("U_b")).data;  // (B, n, kb)
  const mask = (await get("mask")).data;  // (B, n)
  const recT = await get("rec_T");  // (E, kr, kb)
  const recSrc = (await get("rec_src")).data, recDst = (await get("rec_dst")).data;
  const recSide = (await get("rec_side")).data;
  const urt = await get("U_r_turned");  // (4, n, kr)
  const W = (await get("W")).data;  // (B, 3, kb, kb)
  const V = (await get("V")).data;  // (B, 4, 3, kb, kr)
  const albedo = (await get("albedo")).data;  // (B, n, 3)
  const fill = (await get("fill_index")).data;
  const [nb, kb, n] = tdb.shape;
  const kr = urt.shape[2];
  const edges = recT.shape[0];
  const feedback = manifest.config.runtime.feedback;
  const useR = manifest.config.interfaces.enabled && edges > 0;
  const res = manifest.lightmap.resolution;
  const T = tdb.data, R = recT.data, U = urt.data;
  const incident = new Float32Array(nb * n * 3);  // albedo-free incident light / pi at every texel
  // layer 0: the incident light (set per lighting), layer 1: the texel albedo
  const texture = layerTexture(fill, res, 2, (k, t) => (k === 0 ? [0, 0, 0]
    : [albedo[t * 3], albedo[t * 3 + 1], albedo[t * 3 + 2]]));
  const material = new THREE.ShaderMaterial({
    glslVersion: THREE.GLSL3,
    side: THREE.DoubleSide,
    uniforms: { layers: { value: texture } },
    vertexShader: VERTEX_UV,
    fragmentShader: `
      precision highp float;
      precision highp sampler2DArray;
      uniform sampler2DArray layers;
      in vec2 vLightmapUv;
      out vec4 radiance;
      void main() {
        vec3 e = texture(layers, vec3(vLightmapUv, 0.0)).rgb;
        vec3 a = texture(layers, vec3(vLightmapUv, 1.0)).rgb;
        radiance = vec4(a * e, 1.0);
      }`,
  });
  // r = T_b->r b summed per receiving (block, side): (B * 4, kr, 3)
  const records = (b) => {
    const r = new Float64Array(nb * 4 * kr * 3);
    for (let e = 0; e < edges; e++) {
      const src = recSrc[e], slot = recDst[e] * 4 + recSide[e];
      for (let j = 0; j < kr; j++)
        for (let k = 0; k < kb; k++) {
          const t = R[(e * kr + j) * kb + k];
          for (let ch = 0; ch < 3; ch++) r[(slot * kr + j) * 3 + ch] += t * b[(src * kb + k) * 3 + ch];
        }
    }
    return r;
  };
  return {
    material,
    setLighting({ direct }) {
      if (direct.length !== nb * n) throw new Error(`direct radiance at ${direct.length} texels, the layout has ${nb * n}`);
      // b = T_d->b (direct x mask) per block and channel
      let b = new Float64Array(nb * kb * 3);
      for (let i = 0; i < nb; i++)
        for (let k = 0; k < kb; k++)
          for (let t = 0; t < n; t++) {
            const w = T[(i * kb + k) * n + t] * mask[i * n + t];
            for (let ch = 0; ch < 3; ch++) b[(i * kb + k) * 3 + ch] += w * direct[i * n + t][ch];
          }
      const bTotal = Float64Array.from(b);
      const rTotal = new Float64Array(nb * 4 * kr * 3);
      for (let step = 0; step <= feedback; step++) {
        const r = useR ? records(b) : null;
        if (r) for (let q = 0; q < r.length; q++) rTotal[q] += r[q];
        if (step === feedback) break;
        // the next bounce in the reduced spaces: b' = W b + sum_s V_s r_s (per channel)
        const next = new Float64Array(nb * kb * 3);
        for (let i = 0; i < nb; i++)
          for (let ch = 0; ch < 3; ch++)
            for (let k = 0; k < kb; k++) {
              let acc = 0;
              for (let j = 0; j < kb; j++) acc += W[((i * 3 + ch) * kb + k) * kb + j] * b[(i * kb + j) * 3 + ch];
              if (r)
                for (let s = 0; s < 4; s++)
                  for (let j = 0; j < kr; j++)
                    acc += V[(((i * 4 + s) * 3 + ch) * kb + k) * kr + j] * r[((i * 4 + s) * kr + j) * 3 + ch];
              next[(i * kb + k) * 3 + ch] = acc;
            }
        b = next;
        for (let q = 0; q < b.length; q++) bTotal[q] += b[q];
      }
      // incident light at every texel: (U_b b + sum_s U_r,s r_s) x mask
      for (let i = 0; i < nb; i++)
        for (let t = 0; t < n; t++)
          for (let ch = 0; ch < 3; ch++) {
            let acc = 0;
            for (let k = 0; k < kb; k++) acc += ub[(i * n + t) * kb + k] * bTotal[(i * kb + k) * 3 + ch];
            for (let s = 0; s < 4; s++)
              for (let j = 0; j < kr; j++) acc += U[(s * n + t) * kr + j] * rTotal[((i * 4 + s) * kr + j) * 3 + ch];
            incident[(i * n + t) * 3 + ch] = acc * mask[i * n + t];
          }
      const data = texture.image.data;
      for (let p = 0; p < res * res; p++) {
        const t = fill[p];
        for (let ch = 0; ch < 3; ch++) data[p * 4 + ch] = incident[t * 3 + ch];
      }
      texture.needsUpdate = true;
    },
  };
}

// The relighting material of the export at `base` (its URL, ending in "/"): {material, setLighting}.
export async function relightMaterial(base) {
  const manifest = await json(base + "export.json");
  const make = { sh_prt: shPrt, datadriven: dataDriven, sg_lightfield: sgLightfield, mrt }[manifest.method];
  if (!make) throw new Error(`relight.js relights SH PRT, data-driven PRT, SG light-field texture and MRT exports, ` +
                             `not ${manifest.method}`);
  return make(base, manifest);
}
