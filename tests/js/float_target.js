// The browser tests' readback: `scene` drawn by `camera` into a float RGBA target of width x height,
// cleared to 0 (alpha 0 where nothing is drawn); returns its pixels as GL reads them (bottom row first).
import * as THREE from "three";

export function renderToFloat(renderer, scene, camera, width, height, depthBuffer = true) {
  const target = new THREE.WebGLRenderTarget(width, height, { type: THREE.FloatType, format: THREE.RGBAFormat,
                                                              depthBuffer });
  renderer.setRenderTarget(target);
  renderer.setClearColor(0x000000, 0.0);
  renderer.clear();
  renderer.render(scene, camera);
  const pixels = new Float32Array(width * height * 4);
  renderer.readRenderTargetPixels(target, 0, 0, width, height, pixels);
  renderer.setRenderTarget(null);
  target.dispose();
  return pixels;
}
