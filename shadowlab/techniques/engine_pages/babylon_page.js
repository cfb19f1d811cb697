// shadowlab's Babylon.js adapter page (@babylonjs/core 9, @babylonjs/loaders; served from node_modules
// on 127.0.0.1).
//
// window.shadowlab.load(cfg) loads the exported glb once (Babylon's left-handed world, see W3);
// window.shadowlab.render(params) builds the light's ShadowGenerator (or CascadedShadowGenerator)
// with the engine's own properties and returns, per light, the engine's shadow term alone as
// visibility in [0, 1]: with only that light enabled, every surface drawn with a white
// StandardMaterial (no specular, no ambient) into a float render target (the camera's
// outputRenderTarget), once with shadows received and once without; visibility is their ratio
// (the light's colour summed), 1 where the light does not reach (unlit below 1e-7).
// only the modules used (the whole of @babylonjs/core is ~3400 modules: half a minute to load)
import { Engine } from '@babylonjs/core/Engines/engine.js';
import { Scene } from '@babylonjs/core/scene.js';
import { Matrix, Vector3 } from '@babylonjs/core/Maths/math.vector.js';
import { Color3, Color4 } from '@babylonjs/core/Maths/math.color.js';
import { UniversalCamera } from '@babylonjs/core/Cameras/universalCamera.js';
import { Camera } from '@babylonjs/core/Cameras/camera.js';
import { DirectionalLight } from '@babylonjs/core/Lights/directionalLight.js';
import { SpotLight } from '@babylonjs/core/Lights/spotLight.js';
import '@babylonjs/core/Lights/pointLight.js';
import { ShadowGenerator } from '@babylonjs/core/Lights/Shadows/shadowGenerator.js';
import { CascadedShadowGenerator } from '@babylonjs/core/Lights/Shadows/cascadedShadowGenerator.js';
import '@babylonjs/core/Lights/Shadows/shadowGeneratorSceneComponent.js';
import { StandardMaterial } from '@babylonjs/core/Materials/standardMaterial.js';
import { Material } from '@babylonjs/core/Materials/material.js';
import { RenderTargetTexture } from '@babylonjs/core/Materials/Textures/renderTargetTexture.js';
import { Texture } from '@babylonjs/core/Materials/Textures/texture.js';
import { Constants } from '@babylonjs/core/Engines/constants.js';
import { AppendSceneAsync } from '@babylonjs/core/Loading/sceneLoader.js';
import '@babylonjs/core/Loading/loadingScreen.js';
import '@babylonjs/loaders/glTF/2.0/index.js';
import { lightItem, publish } from './page_common.js';

const BABYLON = { Engine, Scene, Matrix, Vector3, Color3, Color4, UniversalCamera, Camera, DirectionalLight, SpotLight,
                  ShadowGenerator, CascadedShadowGenerator, StandardMaterial, Material, RenderTargetTexture, Texture,
                  Constants };

const S = {};
const MAX_SPOT = Math.PI * 160 / 180;     // full cone
// glTF's right-handed world as Babylon's left-handed one: the loader's __root__ node maps (x, y, z) to
// (-x, y, z) (it scales z by -1 and turns 180° about y), so the truth's camera and lights are mapped alike
const W3 = (v) => new BABYLON.Vector3(-v[0], v[1], v[2]);

async function load(cfg) {
  const W = cfg.width, H = cfg.height;
  const canvas = document.createElement('canvas');
  canvas.width = W; canvas.height = H;
  canvas.style.width = W + 'px'; canvas.style.height = H + 'px';
  document.body.appendChild(canvas);
  const engine = new BABYLON.Engine(canvas, false, { preserveDrawingBuffer: true, stencil: true,
    antialias: false, premultipliedAlpha: false }, false);
  engine.setHardwareScalingLevel(1);
  engine.setSize(W, H);
  const scene = new BABYLON.Scene(engine);
  scene.clearColor = new BABYLON.Color4(0, 0, 0, 0);
  scene.ambientColor = new BABYLON.Color3(0, 0, 0);
  scene.imageProcessingConfiguration.isEnabled = false;
  const blob = await (await fetch(cfg.glb)).arrayBuffer();
  await AppendSceneAsync(new Uint8Array(blob), scene, { pluginExtension: '.glb' });

  const meshes = scene.meshes.filter((m) => m.getTotalVertices() > 0);
  let lo = new BABYLON.Vector3(Infinity, Infinity, Infinity), hi = lo.scale(-1);
  for (const m of meshes) {
    m.computeWorldMatrix(true);
    const b = m.getBoundingInfo().boundingBox;
    lo = BABYLON.Vector3.Minimize(lo, b.minimumWorld); hi = BABYLON.Vector3.Maximize(hi, b.maximumWorld);
  }
  const centre = lo.add(hi).scale(0.5), radius = hi.subtract(lo).length() / 2;

  const cam = cfg.camera;
  const eye = W3(cam.position);
  const camera = new BABYLON.UniversalCamera('truth', eye, scene);
  camera.upVector = W3(cam.up);
  camera.setTarget(W3(cam.target));
  camera.fov = cam.fovY * Math.PI / 180;
  camera.fovMode = BABYLON.Camera.FOVMODE_VERTICAL_FIXED;
  const fwd = W3(cam.target).subtract(eye).normalize();
  const zc = BABYLON.Vector3.Dot(centre.subtract(eye), fwd);
  camera.minZ = Math.max(cam.near, (zc - radius) * 0.5, 1e-3);
  camera.maxZ = Math.max(Math.min(cam.far, (zc + radius) * 1.05 + 1e-3), camera.minZ * 2);
  scene.activeCamera = camera;

  const materials = meshes.map((m) => {
    const mat = new BABYLON.StandardMaterial('white_' + m.name, scene);
    mat.diffuseColor = new BABYLON.Color3(1, 1, 1);
    mat.specularColor = new BABYLON.Color3(0, 0, 0);
    mat.emissiveColor = new BABYLON.Color3(0, 0, 0);
    mat.ambientColor = new BABYLON.Color3(0, 0, 0);
    mat.backFaceCulling = false;
    mat.twoSidedLighting = true;
    const m0 = m.material;
    if (m0 && m0.alphaMode !== undefined && m0.transparencyMode === BABYLON.Material.MATERIAL_ALPHATEST) {
      mat.diffuseTexture = m0.albedoTexture; mat.useAlphaFromDiffuseTexture = true;
      mat.alphaCutOff = m0.alphaCutOff; mat.transparencyMode = BABYLON.Material.MATERIAL_ALPHATEST;
    }
    m.material = mat;
    m.receiveShadows = true;
    return mat;
  });

  const lights = [];
  for (const L of cfg.lights) {
    const light = scene.lights.find((l) => l.name === L.name);
    if (!light) throw new Error(`no Babylon light named ${L.name} in the glb (KHR_lights_punctual)`);
    light.parent = null;
    const dir = W3(L.direction).normalize();
    if (light instanceof BABYLON.DirectionalLight) {
      light.direction = dir;
      light.position = centre.subtract(dir.scale(radius + 1.0));
    } else {
      light.position = W3(L.position);
      if (light instanceof BABYLON.SpotLight) {
        light.direction = dir;
        if (light.angle > MAX_SPOT) {
          // a rect or disk light is a 90° glTF spot (its hemisphere, a 180° Babylon cone), which a
          // perspective shadow map cannot hold: narrow the cone to the scene's box from the light
          let a = 0;
          for (let c = 0; c < 8; c++) {
            const v = new BABYLON.Vector3(c & 1 ? hi.x : lo.x, c & 2 ? hi.y : lo.y, c & 4 ? hi.z : lo.z)
              .subtract(light.position);
            const cos = BABYLON.Vector3.Dot(v, dir) / Math.max(v.length(), 1e-9);
            if (cos > 0) a = Math.max(a, Math.acos(Math.min(cos, 1)));
          }
          light.angle = Math.min(Math.max(2.04 * a, 0.04), MAX_SPOT);
          light.innerAngle = 0;
        }
      }
    }
    lights.push({ name: L.name, light });
  }
  const rt = new BABYLON.RenderTargetTexture('vis', { width: W, height: H }, scene, false, true,
    BABYLON.Constants.TEXTURETYPE_FLOAT, false, BABYLON.Texture.NEAREST_SAMPLINGMODE, true, false, false,
    BABYLON.Constants.TEXTUREFORMAT_RGBA);
  rt.clearColor = new BABYLON.Color4(0, 0, 0, 0);
  camera.outputRenderTarget = rt;
  Object.assign(S, { cfg, engine, scene, camera, meshes, materials, lights, rt, W, H, gen: null, centre, radius,
                     sentLit: new Set() });
  return { version: BABYLON.Engine.Version, webgl2: engine.webGLVersion === 2, near: camera.minZ, far: camera.maxZ,
           lights: lights.map((l) => l.light.getClassName()), sphere: [centre.x, centre.y, centre.z, radius] };
}

const QUALITY = { high: 0, medium: 1, low: 2 };

function makeGenerator(type, light, p) {
  let g;
  if (type === 'csm') {
    g = new BABYLON.CascadedShadowGenerator(p.mapSize, light);
    g.numCascades = p.numCascades;
    g.lambda = p.lambda;
    g.cascadeBlendPercentage = p.cascadeBlendPercentage;
    g.stabilizeCascades = p.stabilizeCascades;
    g.autoCalcDepthBounds = p.autoCalcDepthBounds;
    g.filteringQuality = QUALITY[p.filteringQuality];
  } else {
    g = new BABYLON.ShadowGenerator(p.mapSize, light);
    if (type === 'pcf') { g.usePercentageCloserFiltering = true; g.filteringQuality = QUALITY[p.filteringQuality]; }
    if (type === 'poisson') g.usePoissonSampling = true;
    if (type === 'pcss') {
      g.useContactHardeningShadow = true;
      g.filteringQuality = QUALITY[p.filteringQuality];
      g.contactHardeningLightSizeUVRatio = p.contactHardeningLightSizeUVRatio;
    }
    if (type === 'esm') g.useExponentialShadowMap = true;
    if (type === 'esm_blur') {
      g.useBlurExponentialShadowMap = true;
      g.blurScale = p.blurScale; g.blurBoxOffset = p.blurBoxOffset;
      g.useKernelBlur = p.useKernelBlur; g.blurKernel = p.blurKernel;
    }
    if (type === 'esm_close') g.useCloseExponentialShadowMap = true;
    if (p.depthScale !== undefined) g.depthScale = p.depthScale;
  }
  g.bias = p.bias;
  g.normalBias = p.normalBias;
  // not set (0): the scene's depth range from the light (Babylon would take the camera's planes,
  // which here bound the view, not what the light sees)
  const d = BABYLON.Vector3.Distance(light.position, S.centre);
  light.shadowMinZ = p.shadowMinZ > 0 ? p.shadowMinZ : Math.max(0.05, d - S.radius);
  light.shadowMaxZ = p.shadowMaxZ > 0 ? p.shadowMaxZ : d + S.radius * 1.01 + 0.1;
  for (const m of S.meshes) if (castsShadows(m)) g.addShadowCaster(m, false);
  return g;
}

// a shape with casts_shadows = false (the glb node's extras.shadowlab, which the loader keeps in
// metadata.gltf.extras): drawn and lit, never a caster
function castsShadows(m) {
  for (let n = m; n; n = n.parent) {
    const x = n.metadata && n.metadata.gltf && n.metadata.gltf.extras && n.metadata.gltf.extras.shadowlab;
    if (x && x.casts_shadows === false) return false;
  }
  return true;
}

async function draw(receive) {
  for (const m of S.meshes) m.receiveShadows = receive;
  await S.scene.whenReadyAsync();
  S.scene.render();
  return await S.rt.readPixels(0, 0, null, true, false, 0, 0, S.W, S.H);
}

// the generator's shadow camera as the map was rendered with it, for shadowlab's transfer: the
// world -> clip matrix in shadowlab's (right-handed, W3) coordinates, row vectors as Babylon's, and the
// depth range of the depth metric (z_clip + minZ) / (minZ + maxZ) that the map stores
function shadowCamera(gen, light) {
  const flip = BABYLON.Matrix.Scaling(-1, 1, 1);
  const m = flip.multiply(gen.getTransformMatrix());
  const cam = S.scene.activeCamera;
  return { resolution: gen.getShadowMap().getSize().width, projection: 'matrix', matrix: Array.from(m.m),
           minZ: light.getDepthMinZ(cam), maxZ: light.getDepthMaxZ(cam) };
}

async function render(p) {
  const t0 = performance.now();
  const out = [], maps = [];
  for (const entry of S.lights) {
    for (const e of S.lights) e.light.setEnabled(e === entry);
    const light = entry.light;
    const saved = [light.shadowMinZ, light.shadowMaxZ];
    const type = p.__type || S.cfg.type;
    const gen = makeGenerator(type, light, p);
    const sh = new Float32Array(await draw(true));
    const lit = new Float32Array(await draw(false));
    const count = type === 'csm' ? gen.numCascades : 1;
    maps.push(type === 'csm' ? Array.from({ length: count }, () => ({ resolution: gen.getShadowMap().getSize().width }))
                             : [shadowCamera(gen, light)]);
    gen.dispose();
    [light.shadowMinZ, light.shadowMaxZ] = saved;
    out.push(lightItem(entry.name, lit, sh, S.W * S.H, S.sentLit));
  }
  return { lights: out, maps, ms: performance.now() - t0 };
}

publish(load, render, S);
