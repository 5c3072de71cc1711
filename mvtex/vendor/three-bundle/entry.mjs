// The parts of three.js that mvtex's viewer (mvtex/web/viewer.js) uses, bundled into one
// classic script, global THREE (see ../README.md).
export {
  Box3, BufferAttribute, Color, ColorManagement, DataTexture, DoubleSide, FloatType, GLSL3, LinearFilter,
  LinearMipmapLinearFilter, LinearSRGBColorSpace, Matrix4, NearestFilter, NoColorSpace, NoToneMapping,
  PerspectiveCamera, REVISION, RGFormat, RepeatWrapping, Scene, ShaderMaterial, Sphere, Vector2, Vector3,
  WebGLRenderer,
} from 'three';
export { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
export { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
