// The parts of three.js the console's avatar view uses; scripts/vendor-console.sh bundles this
// file with esbuild into console/vendor/viewer.js (one minified ES module, no network at run time).
export {
    AmbientLight,
    Box3,
    Color,
    DirectionalLight,
    PerspectiveCamera,
    Scene,
    SRGBColorSpace,
    Vector3,
    WebGLRenderer,
} from 'three';
export { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
export { OrbitControls } from 'three/addons/controls/OrbitControls.js';
