// Babylon.js (npm @babylonjs/core + @babylonjs/loaders) loading a glTF with EXT_lights_image_based
// and drawing a mirror sphere and a matte sphere lit only by it, read back as linear floats.
//
// Served by tests/test_babylon.py next to tests/js/node_modules (the page's import map points
// "@babylonjs/core/" and "@babylonjs/loaders/" there). The page exposes window.babylonIbl:
//   load(url)                 append the glTF to a fresh engine and scene (Babylon's default,
//                             left-handed); returns what Babylon made of the light
//   setGammaSpace(bool)       the environment texture's gammaSpace (Babylon 9 loads it as true)
//   look(dirs, kind)          for each glTF-frame direction d: place an orthographic camera on
//                             the side d of a unit sphere ("mirror": metallic 1, roughness 0;
//                             "matte": metallic 0, roughness 1, F0 0), render into a float
//                             target and return the centre pixel's linear RGB. The mirror's
//                             centre pixel reflects the view back, so it shows the environment
//                             toward d; the matte one's normal there is d.
// Directions go from the glTF frame to Babylon's world through the inverse-transpose of the
// loader's "__root__" node world matrix (Babylon's own conversion of the asset), never by a
// formula written here.
import { Engine } from "@babylonjs/core/Engines/engine.js";
import { Scene } from "@babylonjs/core/scene.js";
import { Vector3, Matrix } from "@babylonjs/core/Maths/math.vector.js";
import { Color3 } from "@babylonjs/core/Maths/math.color.js";
import { FreeCamera } from "@babylonjs/core/Cameras/freeCamera.js";
import { Camera } from "@babylonjs/core/Cameras/camera.js";
import { CreateSphere } from "@babylonjs/core/Meshes/Builders/sphereBuilder.js";
import { PBRMaterial } from "@babylonjs/core/Materials/PBR/pbrMaterial.js";
import { RenderTargetTexture } from "@babylonjs/core/Materials/Textures/renderTargetTexture.js";
import { Constants } from "@babylonjs/core/Engines/constants.js";
import { AppendSceneAsync } from "@babylonjs/core/Loading/sceneLoader.js";
// side effects the deep imports need: the loading screen the loader shows, and
// BaseTexture.sphericalPolynomial (without it the PBR shader's irradiance is silently zero)
import "@babylonjs/core/Loading/loadingScreen.js";
import "@babylonjs/core/Materials/Textures/baseTexture.polynomial.js";
import "@babylonjs/loaders/glTF/index.js";

const SIZE = 33; // odd: one centre pixel
const ONE_NODE = { asset: { version: "2.0" }, scene: 0, scenes: [{ nodes: [0] }],
                   nodes: [{ name: "probe" }] };

const state = { engine: null, scene: null, toBabylon: null, spheres: {}, rtt: null, cam: null };

async function load(url) {
    if (state.engine) state.engine.dispose();
    state.spheres = {};
    const canvas = document.getElementById("c");
    const engine = new Engine(canvas, false, { preserveDrawingBuffer: true, antialias: false });
    const scene = new Scene(engine);
    // linear output: image processing (tone mapping, exposure, gamma) is left to a post
    // process, and none is attached; the materials then only clamp to [0, 30]
    scene.imageProcessingConfiguration.applyByPostProcess = true;
    await AppendSceneAsync(url, scene);
    const env = scene.environmentTexture;
    if (!env) throw new Error("no environment texture after loading " + url);
    await new Promise((resolve) => {
        const poll = () => (env.isReady() ? resolve() : setTimeout(poll, 10));
        poll();
    });
    // The environment file has no nodes; a one-node glTF appended to the same scene shows
    // where Babylon's loader puts glTF space (its "__root__" node).
    await AppendSceneAsync("data:" + JSON.stringify(ONE_NODE), scene);
    const root = scene.getMeshByName("__root__");
    if (!root) throw new Error("the glTF loader made no __root__ node");
    const world = root.computeWorldMatrix(true);
    const inv = world.clone().invert();
    state.toBabylon = Matrix.Transpose(inv); // normals/directions: inverse transpose
    state.engine = engine;
    state.scene = scene;

    const mirror = new PBRMaterial("mirror", scene);
    mirror.metallic = 1.0;
    mirror.roughness = 0.0;
    mirror.albedoColor = new Color3(1, 1, 1);
    const matte = new PBRMaterial("matte", scene);
    matte.metallic = 0.0;
    matte.roughness = 1.0;
    matte.metallicF0Factor = 0.0; // no specular reflection: the diffuse term alone
    matte.albedoColor = new Color3(1, 1, 1);
    for (const [kind, mat] of [["mirror", mirror], ["matte", matte]]) {
        const s = CreateSphere(kind, { diameter: 2, segments: 96 }, scene);
        s.material = mat;
        s.isVisible = false;
        state.spheres[kind] = s;
    }
    const cam = new FreeCamera("cam", new Vector3(0, 0, -5), scene);
    cam.mode = Camera.ORTHOGRAPHIC_CAMERA;
    // a narrow window on the sphere's centre: neighbouring pixels see almost the same direction
    cam.orthoLeft = -0.05; cam.orthoRight = 0.05; cam.orthoBottom = -0.05; cam.orthoTop = 0.05;
    cam.minZ = 0.1; cam.maxZ = 20;
    scene.activeCamera = cam;
    state.cam = cam;
    const rtt = new RenderTargetTexture("readback", SIZE, scene,
        { type: Constants.TEXTURETYPE_FLOAT, generateMipMaps: false });
    rtt.activeCamera = cam;
    rtt.clearColor = { r: 0, g: 0, b: 0, a: 0 };
    scene.customRenderTargets.push(rtt);
    state.rtt = rtt;
    await scene.whenReadyAsync();
    return { gammaSpace: env.gammaSpace,
             level: env.level, lodGenerationScale: env.lodGenerationScale,
             size: env.getSize().width, isCube: env.isCube,
             root: Array.from(world.m),
             version: Engine.Version, readbackType: rtt.getInternalTexture().type };
}

async function look(dirs, kind) {
    const { scene, rtt, cam } = state;
    for (const k of Object.keys(state.spheres)) state.spheres[k].isVisible = (k === kind);
    rtt.renderList = [state.spheres[kind]];
    while (!state.spheres[kind].isReady(true) || !rtt.isReadyForRendering()) {
        await new Promise((r) => setTimeout(r, 10));
    }
    const out = [];
    for (const d of dirs) {
        const w = Vector3.TransformNormal(new Vector3(d[0], d[1], d[2]), state.toBabylon).normalize();
        cam.position = w.scale(5);
        // an up vector not parallel to the view
        cam.upVector = Math.abs(w.y) > 0.9 ? new Vector3(0, 0, 1) : new Vector3(0, 1, 0);
        cam.setTarget(Vector3.Zero());
        cam.computeWorldMatrix(true);
        scene.render();
        await new Promise((r) => { rtt.onAfterRenderObservable.addOnce(() => r()); rtt.render(); });
        const px = await rtt.readPixels();
        const c = (SIZE * ((SIZE - 1) / 2) + (SIZE - 1) / 2) * 4;
        out.push([px[c], px[c + 1], px[c + 2]]);
    }
    return out;
}

function setGammaSpace(value) {
    state.scene.environmentTexture.gammaSpace = value;
    // materials already drawn keep their shader defines until marked dirty
    state.scene.markAllMaterialsAsDirty(Constants.MATERIAL_TextureDirtyFlag);
    return state.scene.environmentTexture.gammaSpace;
}

window.babylonIbl = { load, look, setGammaSpace, ready: true };
