// RRF indirect radiance as a three.js full-screen pass over a G-buffer (written by jprt export).
// rrf.glsl is Eq. 9 of Ren et al. 2013 as GLSL ES 3.00 functions, rrf_data.bin its numbers (an R32F
// texture); this module wraps them in a ShaderMaterial that reads one G-buffer texel per pixel
// (deferred shading: the engine's own G-buffer, or the one jprt rendered) and outputs linear
// indirect radiance in rgb, alpha 1 where a surface with a network is seen.
import * as THREE from "three";

const FRAGMENT = (source) => `precision highp float;
precision highp int;
precision highp sampler2D;
${source}
uniform sampler2D gPosition;  // xyz: world position
uniform sampler2D gNormal;    // xyz: unit normal, facing the viewer
uniform sampler2D gView;      // xyz: unit direction from the surface to the camera
uniform sampler2D gDiffuse;   // rgb: diffuse albedo
uniform sampler2D gSpecular;  // rgb: specular albedo, a: GGX roughness (alpha)
uniform sampler2D gObject;    // r: object id, -1 where no surface counts
uniform int lightCount;
uniform vec3 lightPos[RRF_MAX_LIGHTS];
uniform vec3 lightRGB[RRF_MAX_LIGHTS];
out vec4 outColor;
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  int object = int(round(texelFetch(gObject, p, 0).r));
  if (object < 0) { outColor = vec4(0.0); return; }
  vec4 s = texelFetch(gSpecular, p, 0);
  float x[RRF_D];
  rrfInputs(texelFetch(gPosition, p, 0).xyz, texelFetch(gView, p, 0).xyz, texelFetch(gNormal, p, 0).xyz,
            texelFetch(gDiffuse, p, 0).rgb, s.rgb, s.a, x);
  outColor = vec4(rrfIndirect(x, object, lightCount, lightPos, lightRGB), 1.0);
}`;

function floatTexture(array, width, height, format) {
  const t = new THREE.DataTexture(array, width, height, format, THREE.FloatType);
  t.minFilter = THREE.NearestFilter;
  t.magFilter = THREE.NearestFilter;
  t.generateMipmaps = false;
  t.needsUpdate = true;
  return t;
}

// rrfPass(url): url is the export folder (ending in "/"). Returns
//   material: the ShaderMaterial (draw it on `quad`, a full-screen triangle pair, into a target the
//             size of the G-buffer; a float target keeps the radiance unclipped),
//   quad:     a Mesh of a 2 x 2 plane in clip space,
//   setGBuffer(fields, width, height): fields {position, normal, view, diffuse, specular, object},
//             each a Float32Array of width x height RGBA texels, row 0 first (the pass writes pixel
//             (x, y) from texel (x, y)),
//   setLighting({position: [[x, y, z], ...], intensity: [[r, g, b], ...]}): point lights, as
//             jprt.inputs.PointLights (at most RRF_MAX_LIGHTS).
export async function rrfPass(url) {
  const manifest = await (await fetch(url + "export.json")).json();
  const g = manifest.glsl;
  const source = await (await fetch(url + g.source)).text();
  const numbers = new Float32Array(await (await fetch(url + g.data)).arrayBuffer());
  const uniforms = {
    rrfData: { value: floatTexture(numbers, g.data_width, g.data_height, THREE.RedFormat) },
    lightCount: { value: 0 },
    lightPos: { value: Array.from({ length: g.max_lights }, () => new THREE.Vector3()) },
    lightRGB: { value: Array.from({ length: g.max_lights }, () => new THREE.Vector3()) },
  };
  for (const name of ["gPosition", "gNormal", "gView", "gDiffuse", "gSpecular", "gObject"]) uniforms[name] = { value: null };
  const material = new THREE.ShaderMaterial({
    glslVersion: THREE.GLSL3, uniforms, depthTest: false, depthWrite: false,
    vertexShader: "void main() { gl_Position = vec4(position.xy, 0.0, 1.0); }",
    fragmentShader: FRAGMENT(source),
  });
  const quad = new THREE.Mesh(new THREE.PlaneGeometry(2, 2), material);
  quad.frustumCulled = false;
  return {
    material, quad,
    setGBuffer(fields, width, height) {
      const names = { position: "gPosition", normal: "gNormal", view: "gView", diffuse: "gDiffuse",
                      specular: "gSpecular", object: "gObject" };
      for (const [key, uniform] of Object.entries(names)) {
        if (!fields[key]) throw new Error(`G-buffer field ${key} missing`);
        uniforms[uniform].value = floatTexture(fields[key], width, height, THREE.RGBAFormat);
      }
    },
    setLighting(lighting) {
      const n = lighting.position.length;
      if (n > g.max_lights) throw new Error(`${n} lights: this pass sums at most ${g.max_lights}`);
      uniforms.lightCount.value = n;
      for (let k = 0; k < n; k++) {
        uniforms.lightPos.value[k].fromArray(lighting.position[k]);
        uniforms.lightRGB.value[k].fromArray(lighting.intensity[k]);
      }
    },
  };
}
