// shadowlab's three.js adapter page (three r187, served from node_modules on 127.0.0.1).
//
// window.shadowlab.load(cfg) loads the exported glb once; window.shadowlab.render(params) sets the
// engine's shadow parameters and returns, per light, the engine's shadow term alone as visibility
// in [0, 1]: with only that light visible, every surface drawn with a white MeshLambertMaterial
// into an RGBA32F render target, once with shadows received and once without; visibility is
// their ratio (the light's colour summed), 1 where the light does not reach (unlit below 1e-7).
// The shadow term is then exactly what three.js multiplies the light's direct light by
// (getShadow / the CSM chunk), whatever filter, bias or cascade blend produced it.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { CSM } from 'three/addons/csm/CSM.js';
import { lightItem, publish } from './page_common.js';

const TYPES = { basic: THREE.BasicShadowMap, pcf: THREE.PCFShadowMap, vsm: THREE.VSMShadowMap, csm: THREE.PCFShadowMap };
const SHADOW_SIDE = { [THREE.FrontSide]: THREE.BackSide, [THREE.BackSide]: THREE.FrontSide,
                      [THREE.DoubleSide]: THREE.DoubleSide };

const S = { };
const MAX_SPOT = THREE.MathUtils.degToRad(80);

// a shape with casts_shadows = false (the glb node's extras.shadowlab, which GLTFLoader puts in
// userData): drawn and lit, never a caster
function castsShadows(o) {
  for (let n = o; n; n = n.parent) {
    const x = n.userData && n.userData.shadowlab;
    if (x && x.casts_shadows === false) return false;
  }
  return true;
}

function lambert(meshes, type) {
  // a fresh white Lambert material per mesh (fresh: the CSM addon's onBeforeCompile must run for it)
  return meshes.map((o) => {
    const m0 = o.userData.glTFMaterial;
    const m = new THREE.MeshLambertMaterial({ color: 0xffffff, side: THREE.DoubleSide });
    m.shadowSide = (m0.shadowSide !== null && m0.shadowSide !== undefined) ? m0.shadowSide
      : (type === 'vsm' ? m0.side : SHADOW_SIDE[m0.side]);
    if (m0.alphaTest > 0) { m.alphaTest = m0.alphaTest; m.map = m0.map; m.alphaMap = m0.alphaMap; }
    if (o.material !== m0) o.material.dispose();
    o.material = m;
    return m;
  });
}

function findLight(obj) {
  let found = null;
  obj.traverse((o) => { if (!found && o.isLight) found = o; });
  return found;
}

async function load(cfg) {
  const W = cfg.width, H = cfg.height;
  const canvas = document.createElement('canvas');
  canvas.width = W; canvas.height = H;
  document.body.appendChild(canvas);
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, alpha: false, precision: 'highp',
                                             powerPreference: 'high-performance' });
  renderer.setPixelRatio(1);
  renderer.setSize(W, H, false);
  renderer.toneMapping = THREE.NoToneMapping;
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  renderer.shadowMap.enabled = true;
  renderer.shadowMap.type = TYPES[cfg.type];
  renderer.shadowMap.autoUpdate = true;
  renderer.setClearColor(0x000000, 0);

  const gltf = await new GLTFLoader().loadAsync(cfg.glb);
  const scene = gltf.scene;
  scene.updateMatrixWorld(true);

  // the truth's camera: the same vertical field of view, aspect, position, target and up; near and
  // far bound the scene (they shape only the depth buffer, not which pixel sees which point)
  const box = new THREE.Box3().setFromObject(scene, true);
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  const cam = cfg.camera;
  const eye = new THREE.Vector3(...cam.position);
  const fwd = new THREE.Vector3(...cam.target).sub(eye).normalize();
  const zc = sphere.center.clone().sub(eye).dot(fwd);
  const near = Math.max(cam.near, (zc - sphere.radius) * 0.5, 1e-3);
  const far = Math.min(cam.far, (zc + sphere.radius) * 1.05 + 1e-3);
  const camera = new THREE.PerspectiveCamera(cam.fovY, W / H, near, Math.max(far, near * 2));
  camera.position.copy(eye);
  camera.up.set(...cam.up);
  camera.lookAt(new THREE.Vector3(...cam.target));
  camera.updateMatrixWorld(true);
  camera.updateProjectionMatrix();

  // every surface: white Lambert, seen from both sides by the camera (the truth's rays hit both),
  // casting into the shadow map with the side three.js would use for the glTF material
  const meshes = [];
  scene.traverse((o) => {
    if (!o.isMesh) return;
    const m0 = o.material;
    o.userData.glTFMaterial = m0;
    o.castShadow = castsShadows(o);
    o.receiveShadow = true;
    meshes.push(o);
  });
  const materials = lambert(meshes, cfg.type);

  // the lights of the manifest, in the truth's order
  const lights = [];
  for (const L of cfg.lights) {
    const node = await gltf.parser.getDependency('node', L.node);
    const light = findLight(node);
    if (!light) throw new Error(`glTF node ${L.node} (light ${L.name}) holds no KHR_lights_punctual light`);
    light.castShadow = cfg.type !== 'csm';
    if (light.isDirectionalLight) {
      // a directional light's shadow camera sits at the light, looking at its target: put the
      // target at the scene's centre and the light (R + 1) behind it, against the light's direction
      const dir = new THREE.Vector3(...L.direction).normalize();
      scene.add(light.target);
      light.target.position.copy(sphere.center);
      const p = sphere.center.clone().addScaledVector(dir, -(sphere.radius + 1.0));
      light.parent.worldToLocal(p);
      light.position.copy(p);
    }
    light.updateMatrixWorld(true);
    if (light.isSpotLight && light.angle > MAX_SPOT) {
      // a rect or disk light is a 90° glTF spot (its hemisphere); three.js's spot shadow camera has
      // twice the cone's angle as its field of view, so narrow the cone to the scene's box as seen
      // from the light (at most MAX_SPOT)
      const pos = light.getWorldPosition(new THREE.Vector3());
      const dir = new THREE.Vector3(...L.direction).normalize();
      let a = 0;
      for (let c = 0; c < 8; c++) {
        const v = new THREE.Vector3(c & 1 ? box.max.x : box.min.x, c & 2 ? box.max.y : box.min.y,
                                    c & 4 ? box.max.z : box.min.z).sub(pos);
        const cos = v.dot(dir) / Math.max(v.length(), 1e-9);
        if (cos > 0) a = Math.max(a, Math.acos(Math.min(cos, 1)));
      }
      light.angle = Math.min(Math.max(a * 1.02, 0.02), MAX_SPOT);
      light.penumbra = 0;
    }
    light.target && light.target.updateMatrixWorld(true);
    lights.push({ name: L.name, light, direction: L.direction });
  }
  const rt = new THREE.WebGLRenderTarget(W, H, { type: THREE.FloatType, format: THREE.RGBAFormat,
    minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter, depthBuffer: true, samples: 0,
    colorSpace: THREE.NoColorSpace });
  Object.assign(S, { cfg, renderer, scene, camera, meshes, materials, lights, rt, W, H, sphere, csm: null,
                     lit: new Float32Array(W * H * 4), shadowed: new Float32Array(W * H * 4), sentLit: new Set() });
  const gl = renderer.getContext();
  return { revision: THREE.REVISION, webgl2: gl instanceof WebGL2RenderingContext,
           renderer: gl.getParameter(gl.RENDERER), near: camera.near, far: camera.far,
           lights: lights.map((l) => l.light.type), sphere: [...sphere.center.toArray(), sphere.radius] };
}

function setShadow(light, p) {
  const sh = light.shadow;
  sh.bias = p.bias;
  sh.normalBias = p.normalBias;
  if (p.radius !== undefined) sh.radius = p.radius;
  if (p.blurSamples !== undefined) sh.blurSamples = p.blurSamples;
  if (sh.mapSize.x !== p.mapSize) {
    sh.mapSize.set(p.mapSize, p.mapSize);
    if (sh.map) { sh.map.dispose(); sh.map = null; }
    if (sh.mapPass) { sh.mapPass.dispose(); sh.mapPass = null; }
  }
  const c = sh.camera;
  c.near = p.near;
  c.far = p.far;
  if (light.isDirectionalLight && p.extent !== undefined) {
    c.left = -p.extent; c.right = p.extent; c.top = p.extent; c.bottom = -p.extent;
  }
  c.updateProjectionMatrix();
  sh.needsUpdate = true;
}

function setupCsm(entry, p) {
  if (S.csm) S.csm.remove();
  S.materials = lambert(S.meshes, S.cfg.type);
  const csm = new CSM({ camera: S.camera, parent: S.scene, cascades: p.cascades, maxFar: p.maxFar, mode: p.mode,
    shadowMapSize: p.shadowMapSize, shadowBias: p.shadowBias, lightDirection: new THREE.Vector3(...entry.direction)
      .normalize(), lightIntensity: entry.light.intensity, lightNear: p.lightNear, lightFar: p.lightFar,
    lightMargin: p.lightMargin });
  csm.fade = p.fade;
  for (const l of csm.lights) { l.color.copy(entry.light.color); l.shadow.normalBias = p.normalBias; }
  for (const m of S.materials) csm.setupMaterial(m);
  csm.updateFrustums();
  S.csm = csm;
}

function draw(receive, out) {
  S.scene.traverse((o) => { if (o.isMesh) o.receiveShadow = receive; });
  if (S.csm) S.csm.update();
  S.renderer.setRenderTarget(S.rt);
  S.renderer.clear();
  S.renderer.render(S.scene, S.camera);
  S.renderer.readRenderTargetPixels(S.rt, 0, 0, S.W, S.H, out);
  S.renderer.setRenderTarget(null);
}

// the light's shadow camera as the map was rendered with it: what shadowlab's transfer needs to turn
// world-unit biases and filter widths into this map's depth and texels
function shadowCamera(light) {
  const c = light.shadow.camera;
  c.updateMatrixWorld(true);
  const e = c.matrixWorld.elements;
  const m = { resolution: light.shadow.mapSize.x, near: c.near, far: c.far,
              position: [e[12], e[13], e[14]], direction: [-e[8], -e[9], -e[10]],
              right: [e[0], e[1], e[2]], up: [e[4], e[5], e[6]] };
  if (c.isOrthographicCamera) Object.assign(m, { projection: 'orthographic', halfWidth: (c.right - c.left) / 2,
                                                 halfHeight: (c.top - c.bottom) / 2 });
  else Object.assign(m, { projection: light.isPointLight ? 'cube' : 'perspective', fovY: c.fov, aspect: c.aspect });
  return m;
}

function render(p) {
  const t0 = performance.now();
  const out = [];
  const maps = [];
  for (const entry of S.lights) {
    for (const e of S.lights) e.light.visible = (e === entry) && S.cfg.type !== 'csm';
    if (S.cfg.type === 'csm') setupCsm(entry, p);
    else setShadow(entry.light, p);
    draw(true, S.shadowed);
    draw(false, S.lit);
    const sm = S.csm ? S.csm.lights.map((l) => ({ resolution: l.shadow.mapSize.x }))
                     : [shadowCamera(entry.light)];
    maps.push(sm);
    out.push(lightItem(entry.name, S.lit, S.shadowed, S.W * S.H, S.sentLit));
    if (S.csm) { S.csm.remove(); S.csm = null; }
  }
  return { lights: out, maps, ms: performance.now() - t0 };
}

publish(load, render, S);
