/* mvtex viewer: a scene of `mvtex export` (scene.glb) that you turn, its texture coordinates
 * blended from the cameras' texture sliding by the eye's position; and the reconstruction's
 * meshes side by side for the demo's report. Needs THREE (mvtex/vendor/three.min.js) and
 * mvtexViewMath (viewmath.js); classic scripts, so that pages open from file://.
 *
 * Drawing follows mvtex's `render_textured` (shaders/textured.frag.glsl): the fabric texture
 * (or the body's matte grey) times 0.25 + 0.75 |n . view|, no colour management, rendered at
 * twice the canvas resolution and reduced by the browser, over the background (40, 40, 46).
 *
 * URL parameters (the page keeps `camera` up to date as you turn the view, so that its
 * address shares the view):
 *   view=NAME | view=A=0.5,B=0.5   the rig camera NAME, or the novel camera of these weights
 *                                  (`mvtex views --weights`: centre and K blended, orientation
 *                                  averaged); default: equal weights over every camera
 *   camera=W,H,fx,fy,cx,cy,rx,ry,rz,tx,ty,tz   any OpenCV camera (rotation as a Rodrigues vector)
 *   texcoords=blend|tg   blended texture sliding (default) or the mesh's own T_G
 *   body=1|0   show the body (default 1); stereo=1   side by side, eyes ipd apart (ipd=0.064 m)
 */
(function (root) {
  'use strict';
  var T = root.THREE, M = root.mvtexViewMath;
  var BACKGROUND = [40 / 255, 40 / 255, 46 / 255];
  var MAX_CAMERAS = 64;

  function decodeBase64(text) {
    var bin = atob(String(text).replace(/\s+/g, ''));
    var out = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out.buffer;
  }

  function parseGLB(buffer) {
    return new Promise(function (resolve, reject) {
      new T.GLTFLoader().parse(buffer, '', resolve, reject);
    });
  }

  /** Record on the viewer's element (and, for a page of its own, on <html>) what a headless
   * browser's test reads: data-viewer = loading | ready | error, data-weights, data-camera. */
  function setAttributes(targets, values) {
    targets.forEach(function (t) {
      Object.keys(values).forEach(function (k) { t.setAttribute(k, String(values[k])); });
    });
  }

  function rowsToMatrix4(rows) {
    var m = new T.Matrix4();
    m.set.apply(m, [].concat(rows[0], rows[1], rows[2], rows[3]));
    return m;
  }

  function applyCamera(cam3, cam, near, far) {
    var pose = M.worldFromGLCamera(cam.R, cam.t);
    cam3.matrixAutoUpdate = true;
    rowsToMatrix4(pose).decompose(cam3.position, cam3.quaternion, cam3.scale);
    cam3.updateMatrixWorld(true);
    setProjection(cam3, cam, near, far);
  }

  function setProjection(cam3, cam, near, far) {
    cam3.projectionMatrix.copy(rowsToMatrix4(M.projectionFromK(cam.K, cam.width, cam.height, near, far)));
    cam3.projectionMatrixInverse.copy(cam3.projectionMatrix).invert();
    cam3.fov = 2 * Math.atan(cam.height / (2 * cam.K[1][1])) * 180 / Math.PI;  // for the controls' panning
    cam3.aspect = cam.width / cam.height;
  }

  function openCVOf(cam3, intrinsics) {
    cam3.updateMatrixWorld(true);
    var e = cam3.matrixWorld.elements;  // column-major
    var rows = [[e[0], e[4], e[8], e[12]], [e[1], e[5], e[9], e[13]], [e[2], e[6], e[10], e[14]], [0, 0, 0, 1]];
    var pose = M.openCVFromWorldGL(rows);
    return { width: intrinsics.width, height: intrinsics.height, K: intrinsics.K, R: pose.R, t: pose.t };
  }

  function depthRange(cam, sphere) {
    var c = M.cameraCentre(cam.R, cam.t);
    var z = cam.R[2][0] * (sphere.center.x - c[0]) + cam.R[2][1] * (sphere.center.y - c[1]) + cam.R[2][2] * (sphere.center.z - c[2]);
    return { near: Math.max((z - sphere.radius) * 0.5, 1e-3), far: Math.max((z + sphere.radius) * 2.0, 1.0) };
  }

  var VERTEX = [
    'uniform sampler2D table;', 'uniform int tableWidth;', 'uniform int numVertices;', 'uniform int numCameras;',
    'uniform float weights[' + MAX_CAMERAS + '];', 'uniform int blend;',
    'out vec3 vCam;', 'out vec3 vNormal;', 'out vec2 vUv;',
    'vec2 lookup(int set) {',
    '  int i = set * numVertices + gl_VertexID;',
    '  return texelFetch(table, ivec2(i % tableWidth, i / tableWidth), 0).rg;',
    '}',
    'void main() {',
    '  vec2 t = lookup(0);',  // T_G
    '  if (blend == 1) {',
    '    t = vec2(0.0);',
    '    for (int c = 0; c < ' + MAX_CAMERAS + '; c++) {',
    '      if (c >= numCameras) break;',
    '      if (weights[c] > 0.0) t += weights[c] * lookup(c + 1);',
    '    }',
    '  }',
    '  vUv = t;',
    '  vec4 cam = modelViewMatrix * vec4(position, 1.0);',
    '  vCam = cam.xyz;',
    '  vNormal = normalMatrix * normal;',
    '  gl_Position = projectionMatrix * cam;',
    '}'].join('\n');

  var FRAGMENT = [
    'uniform sampler2D fabric;', 'uniform vec3 matteColor;', 'uniform int matte;',
    'in vec3 vCam;', 'in vec3 vNormal;', 'in vec2 vUv;', 'out vec4 outColor;',
    'void main() {',
    '  vec3 n = normalize(vNormal);',
    '  vec3 view = normalize(-vCam);',
    '  float lambert = abs(dot(n, view));',
    '  vec3 albedo = matte == 1 ? matteColor : texture(fabric, vUv).rgb;',
    '  outColor = vec4(albedo * (0.25 + 0.75 * lambert), 1.0);',
    '}'].join('\n');

  var BODY_VERTEX = [
    'out vec3 vCam;', 'out vec3 vNormal;', 'out vec2 vUv;',
    'void main() {',
    '  vUv = vec2(0.0);',
    '  vec4 cam = modelViewMatrix * vec4(position, 1.0);',
    '  vCam = cam.xyz;', '  vNormal = normalMatrix * normal;', '  gl_Position = projectionMatrix * cam;',
    '}'].join('\n');

  var COLOR_VERTEX = [
    'in vec3 color;', 'out vec3 vCam;', 'out vec3 vNormal;', 'out vec3 vColor;',
    'void main() {',
    '  vColor = color;', '  vec4 cam = modelViewMatrix * vec4(position, 1.0);',
    '  vCam = cam.xyz;', '  vNormal = normalMatrix * normal;', '  gl_Position = projectionMatrix * cam;',
    '}'].join('\n');

  // As mvtex.render.pictures.render_vertex_colors: the colour times 0.35 + 0.65 |n . view|.
  var COLOR_FRAGMENT = [
    'in vec3 vCam;', 'in vec3 vNormal;', 'in vec3 vColor;', 'out vec4 outColor;',
    'void main() {',
    '  float lambert = abs(dot(normalize(vNormal), normalize(-vCam)));',
    '  outColor = vec4(vColor * (0.35 + 0.65 * lambert), 1.0);',
    '}'].join('\n');

  function texcoordAttribute(geometry, k) {
    var names = k === 0 ? ['uv'] : ['uv' + k, 'texcoord_' + k];
    for (var i = 0; i < names.length; i++) if (geometry.attributes[names[i]]) return geometry.attributes[names[i]];
    throw new Error('scene.glb: the cloth has no TEXCOORD_' + k);
  }

  /** The texcoord sets (T_G, then one per camera) as an RG float texture, set after set. */
  function texcoordTable(geometry, count, maxSize) {
    var n = geometry.attributes.position.count;
    var total = n * count;
    var width = Math.min(maxSize, total);
    var height = Math.ceil(total / width);
    if (height > maxSize) throw new Error('scene.glb: ' + count + ' texcoord sets of ' + n + ' vertices exceed this GPU\'s textures');
    var data = new Float32Array(width * height * 2);
    for (var k = 0; k < count; k++) {
      var a = texcoordAttribute(geometry, k);
      for (var i = 0; i < n; i++) {
        data[2 * (k * n + i)] = a.getX(i);
        data[2 * (k * n + i) + 1] = a.getY(i);
      }
    }
    var tex = new T.DataTexture(data, width, height, T.RGFormat, T.FloatType);
    tex.minFilter = tex.magFilter = T.NearestFilter;
    tex.generateMipmaps = false;
    tex.needsUpdate = true;
    return { texture: tex, width: width, vertices: n };
  }

  function el(tag, attrs, text) {
    var e = document.createElement(tag);
    Object.keys(attrs || {}).forEach(function (k) { e.setAttribute(k, attrs[k]); });
    if (text !== undefined) e.textContent = text;
    return e;
  }

  var STYLE = [
    '.mvtex-viewer{display:flex;flex-direction:column;background:#28282e;color:#ddd;font:13px system-ui,sans-serif}',
    '.mvtex-viewer .mv-stage{flex:1 1 auto;display:flex;align-items:center;justify-content:center;overflow:hidden;min-height:0;position:relative}',
    '.mvtex-viewer canvas{display:block;touch-action:none}',
    '.mvtex-viewer .mv-bar{flex:0 0 44px;height:44px;box-sizing:border-box;display:flex;gap:8px;align-items:center;padding:0 8px;background:#1c1c20;overflow:hidden;white-space:nowrap}',
    '.mvtex-viewer button{background:#3a3a44;color:#eee;border:1px solid #55555f;border-radius:4px;padding:4px 8px;cursor:pointer;font:inherit}',
    '.mvtex-viewer button[aria-pressed="true"]{background:#5a6fa8;border-color:#8ea2dc}',
    '.mvtex-viewer .mv-weights{color:#aab;overflow:hidden;text-overflow:ellipsis;flex:1 1 auto}',
    '.mvtex-viewer .mv-hint{color:#778;flex:0 0 auto}',
    '.mvtex-viewer .mv-label{position:absolute;transform:translate(-50%,-100%);background:rgba(0,0,0,.6);color:#fff;padding:1px 6px;border-radius:3px;pointer-events:none;font-weight:600}',
    '.mvtex-viewer .mv-error{padding:1em;color:#f99}'].join('\n');

  function injectStyle() {
    if (document.getElementById('mvtex-viewer-style')) return;
    var s = el('style', { id: 'mvtex-viewer-style' }, STYLE);
    document.head.appendChild(s);
  }

  function makeRenderer(stage) {
    var renderer = new T.WebGLRenderer({ antialias: false, alpha: false, preserveDrawingBuffer: true });
    renderer.outputColorSpace = T.LinearSRGBColorSpace;
    renderer.toneMapping = T.NoToneMapping;
    renderer.setClearColor(new T.Color(BACKGROUND[0], BACKGROUND[1], BACKGROUND[2]), 1);
    renderer.autoClear = false;
    stage.appendChild(renderer.domElement);
    return renderer;
  }

  /** The scene viewer in `container` for a scene.glb given as base64 text. `params`: a
   * URLSearchParams (default: the page's address). options.page (default true): the viewer is
   * the page, so it keeps the page's address up to date with the view and records its state
   * on <html> too. Resolves to the viewer's state. */
  function openScene(container, base64, params, options) {
    T.ColorManagement.enabled = false;
    injectStyle();
    var page = !options || options.page !== false;
    params = params || new URLSearchParams(page && root.location ? root.location.search : '');
    container.classList.add('mvtex-viewer');
    var stage = el('div', { class: 'mv-stage' });
    var bar = el('div', { class: 'mv-bar' });
    container.appendChild(stage);
    container.appendChild(bar);
    var targets = page ? [container, document.documentElement] : [container];
    setAttributes(targets, { 'data-viewer': 'loading' });
    return parseGLB(decodeBase64(base64)).then(function (gltf) {
      return buildScene(container, stage, bar, gltf, params, targets, page);
    }).catch(function (err) {
      stage.appendChild(el('div', { class: 'mv-error' }, 'mvtex viewer: ' + (err && err.message || err)));
      setAttributes(targets, { 'data-viewer': 'error', 'data-viewer-detail': err && err.message || err });
      console.error(err);
      throw err;
    });
  }

  function buildScene(container, stage, bar, gltf, params, targets, page) {
    var json = gltf.parser.json;
    var info = (json.scenes[json.scene || 0].extras || {}).mvtex;
    if (!info || info.format !== 'mvtex-scene') throw new Error('scene.glb: not an mvtex scene (no extras.mvtex)');
    var cameras = {}, names = [];
    json.nodes.forEach(function (node) {
      var ex = node.extras && node.extras.mvtex;
      if (node.camera === undefined || !ex) return;
      var m = node.matrix;  // column-major world-from-GL-camera (camera nodes are roots)
      var rows = [[m[0], m[4], m[8], m[12]], [m[1], m[5], m[9], m[13]], [m[2], m[6], m[10], m[14]], [0, 0, 0, 1]];
      var pose = M.openCVFromWorldGL(rows);
      cameras[ex.camera] = { width: ex.width, height: ex.height, K: ex.K, R: pose.R, t: pose.t, texcoord: ex.texcoord };
      names.push(ex.camera);
    });
    names.sort(function (a, b) { return cameras[a].texcoord - cameras[b].texcoord; });
    if (!names.length) throw new Error('scene.glb: no cameras');
    if (names.length > MAX_CAMERAS) throw new Error('scene.glb: more than ' + MAX_CAMERAS + ' cameras');
    var centres = names.map(function (n) { return M.cameraCentre(cameras[n].R, cameras[n].t); });

    var cloth = null, body = null;
    gltf.scene.traverse(function (o) {
      if (o.isMesh && o.name === 'cloth') cloth = o;
      if (o.isMesh && o.name === 'body') body = o;
    });
    if (!cloth) throw new Error('scene.glb: no mesh named cloth');
    var renderer = makeRenderer(stage);
    var gl = renderer.getContext();
    var table = texcoordTable(cloth.geometry, names.length + 1, gl.getParameter(gl.MAX_TEXTURE_SIZE));
    var fabric = cloth.material.map;
    fabric.colorSpace = T.NoColorSpace;
    fabric.anisotropy = Math.min(8, renderer.capabilities.getMaxAnisotropy());
    fabric.minFilter = T.LinearMipmapLinearFilter;
    fabric.magFilter = T.LinearFilter;
    fabric.wrapS = fabric.wrapT = T.RepeatWrapping;
    fabric.needsUpdate = true;
    var weightsUniform = new Array(MAX_CAMERAS).fill(0);
    var clothMaterial = new T.ShaderMaterial({
      glslVersion: T.GLSL3, vertexShader: VERTEX, fragmentShader: FRAGMENT, side: T.DoubleSide,
      uniforms: {
        table: { value: table.texture }, tableWidth: { value: table.width }, numVertices: { value: table.vertices },
        numCameras: { value: names.length }, weights: { value: weightsUniform }, blend: { value: 1 },
        fabric: { value: fabric }, matteColor: { value: new T.Vector3(0, 0, 0) }, matte: { value: 0 }
      }
    });
    cloth.material = clothMaterial;
    var bodyColor = info.body_rgb || [168, 163, 156];
    if (body) {
      body.material = new T.ShaderMaterial({
        glslVersion: T.GLSL3, vertexShader: BODY_VERTEX, fragmentShader: FRAGMENT, side: T.DoubleSide,
        uniforms: { fabric: { value: fabric }, matte: { value: 1 },
                    matteColor: { value: new T.Vector3(bodyColor[0] / 255, bodyColor[1] / 255, bodyColor[2] / 255) } }
      });
    }
    var scene = new T.Scene();
    scene.add(gltf.scene);
    var sphere = new T.Box3().setFromObject(gltf.scene).getBoundingSphere(new T.Sphere());
    var clothCentre = new T.Box3().setFromObject(cloth).getCenter(new T.Vector3());

    // the state the URL and the buttons set
    var state = {
      texcoords: params.get('texcoords') === 'tg' ? 'tg' : 'blend',
      body: params.get('body') !== '0',
      stereo: params.get('stereo') === '1',
      ipd: params.has('ipd') ? Number(params.get('ipd')) : 0.064
    };
    if (!(isFinite(state.ipd) && state.ipd >= 0 && state.ipd < 10)) throw new Error('ipd: expected metres in [0, 10)');
    var viewpoint;
    if (params.has('camera')) viewpoint = M.parseCamera(params.get('camera'));
    else if (params.has('view')) viewpoint = M.interpolateCamera(cameras, M.parseView(params.get('view'), names));
    else {
      var equal = {};
      names.forEach(function (n) { equal[n] = 1 / names.length; });
      viewpoint = M.interpolateCamera(cameras, equal);
    }
    var intrinsics = { width: viewpoint.width, height: viewpoint.height, K: viewpoint.K };

    var cam3 = new T.PerspectiveCamera();
    var range = depthRange(viewpoint, sphere);
    applyCamera(cam3, viewpoint, range.near, range.far);
    // The view turns about the first camera's up (its image's -y): the controls keep it upright.
    cam3.up.set(-viewpoint.R[1][0], -viewpoint.R[1][1], -viewpoint.R[1][2]);
    var controls = new T.OrbitControls(cam3, renderer.domElement);
    var axis = new T.Vector3(viewpoint.R[2][0], viewpoint.R[2][1], viewpoint.R[2][2]);
    var eye0 = new T.Vector3().fromArray(M.cameraCentre(viewpoint.R, viewpoint.t));
    var depth = Math.max(axis.dot(clothCentre.clone().sub(eye0)), 0.05);
    controls.target.copy(eye0.clone().addScaledVector(axis, depth));
    applyCamera(cam3, viewpoint, range.near, range.far);  // the controls' constructor turned it to the origin
    controls.enableDamping = false;
    controls.zoomSpeed = 0.6;
    controls.minDistance = 0.05;

    if (!body) state.body = false;
    var buttons = {};
    function button(key, text, onClick) {
      var b = el('button', { type: 'button', 'data-key': key }, text);
      b.addEventListener('click', onClick);
      bar.appendChild(b);
      buttons[key] = b;
      return b;
    }
    button('texcoords', 'texture sliding', function () { state.texcoords = state.texcoords === 'blend' ? 'tg' : 'blend'; update(true); });
    if (body) button('body', 'body', function () { state.body = !state.body; update(true); });
    button('stereo', 'stereo', function () { state.stereo = !state.stereo; layout(); update(true); });
    var readout = el('span', { class: 'mv-weights' });
    bar.appendChild(readout);

    var current = { weights: null, eyes: null };
    function weightsOf(cam) {
      var w = M.weightsForCentre(centres, M.cameraCentre(cam.R, cam.t));
      var out = {};
      names.forEach(function (n, i) { out[n] = w[i]; });
      return out;
    }
    function setWeights(w) {
      for (var i = 0; i < MAX_CAMERAS; i++) weightsUniform[i] = i < names.length ? w[names[i]] : 0;
    }

    function layout() {
      var avail = { w: stage.clientWidth || intrinsics.width, h: stage.clientHeight || intrinsics.height };
      var wide = state.stereo ? 2 * intrinsics.width : intrinsics.width;
      var scale = Math.min(avail.w / wide, avail.h / intrinsics.height);
      if (!(scale > 0)) scale = 1;
      var cssW = Math.floor(wide * scale), cssH = Math.floor(intrinsics.height * scale);
      var dpr = root.devicePixelRatio || 1;
      renderer.setPixelRatio(dpr >= 2 ? dpr : 2 * dpr);
      renderer.setSize(cssW, cssH, true);
    }

    var urlTimer = null;
    function writeURL(cam) {
      if (!page || !root.history || !root.history.replaceState || !root.location) return;
      clearTimeout(urlTimer);
      urlTimer = setTimeout(function () {
        var q = new URLSearchParams(root.location.search);
        q.delete('view');
        q.set('camera', M.formatCamera(cam));
        q.set('texcoords', state.texcoords);
        q.set('body', state.body ? '1' : '0');
        if (state.stereo) q.set('stereo', '1'); else q.delete('stereo');
        try { root.history.replaceState(null, '', '?' + q.toString() + root.location.hash); } catch (e) { /* a sandboxed frame */ }
      }, 300);
    }

    function draw(cam, x, w, h) {
      var r = depthRange(cam, sphere);
      applyCamera(cam3, cam, r.near, r.far);
      renderer.setViewport(x, 0, w, h);
      renderer.setScissor(x, 0, w, h);
      renderer.setScissorTest(true);
      renderer.clear();
      renderer.render(scene, cam3);
    }

    function update(fromUser) {
      var cam = openCVOf(cam3, intrinsics);
      clothMaterial.uniforms.blend.value = state.texcoords === 'blend' ? 1 : 0;
      if (body) body.visible = state.body;
      var size = renderer.getSize(new T.Vector2());
      var eyes = state.stereo ? M.eyeCameras(cam, state.ipd) : [cam];
      var width = size.x / eyes.length;
      current.eyes = [];
      eyes.forEach(function (eye, i) {
        var w = weightsOf(eye);
        current.eyes.push(w);
        setWeights(w);
        draw(eye, i * width, width, size.y);
      });
      applyCamera(cam3, cam, depthRange(cam, sphere).near, depthRange(cam, sphere).far);  // the controls' camera
      current.weights = current.eyes[0];
      current.camera = cam;
      buttons.texcoords.setAttribute('aria-pressed', String(state.texcoords === 'blend'));
      buttons.texcoords.textContent = state.texcoords === 'blend' ? 'texture sliding: blended' : 'texture sliding: off (T_G)';
      if (buttons.body) buttons.body.setAttribute('aria-pressed', String(state.body));
      buttons.stereo.setAttribute('aria-pressed', String(state.stereo));
      function listed(w) {
        return Object.keys(w).filter(function (k) { return w[k] > 5e-4; })
          .map(function (k) { return k + ' ' + w[k].toFixed(3); }).join(', ');
      }
      readout.textContent = state.texcoords !== 'blend' ? 'the inferred mesh with its own texture coordinates (T_G)'
        : state.stereo ? 'weights: left eye ' + listed(current.eyes[0]) + '; right eye ' + listed(current.eyes[1])
          : 'weights: ' + listed(current.weights);
      setAttributes(targets, { 'data-weights': JSON.stringify(current.weights), 'data-camera': M.formatCamera(cam) });
      if (fromUser) writeURL(cam);
    }

    controls.addEventListener('change', function () { update(true); });
    if (root.addEventListener) root.addEventListener('resize', function () { layout(); update(false); });
    bar.appendChild(el('span', { class: 'mv-hint' }, 'drag to turn, right-drag to move, scroll to zoom'));
    layout();
    update(false);
    setAttributes(targets, { 'data-viewer': 'ready' });
    return { names: names, cameras: cameras, current: current, state: state, update: update, renderer: renderer,
             camera: cam3, controls: controls };
  }

  /** The reconstruction's meshes side by side (a GLB of `mvtex.formats.glb.export_glb`, base64),
   * in vertex colours under the light of mvtex's pictures, with each mesh's name above it.
   * frame: {target: [x, y, z], radius, fov_deg}; labels: node name -> text. */
  function openMeshes(container, base64, frame, labels) {
    T.ColorManagement.enabled = false;
    injectStyle();
    container.classList.add('mvtex-viewer');
    var stage = el('div', { class: 'mv-stage' });
    container.appendChild(stage);
    return parseGLB(decodeBase64(base64)).then(function (gltf) {
      var renderer = makeRenderer(stage);
      var material = new T.ShaderMaterial({ glslVersion: T.GLSL3, vertexShader: COLOR_VERTEX,
                                            fragmentShader: COLOR_FRAGMENT, side: T.DoubleSide });
      var tags = [];
      gltf.scene.traverse(function (o) {
        if (!o.isMesh) return;
        if (!o.geometry.attributes.normal) o.geometry.computeVertexNormals();
        o.material = material;
        if (labels && labels[o.name]) {
          var box = new T.Box3().setFromObject(o);
          var tag = el('div', { class: 'mv-label' }, labels[o.name]);
          stage.appendChild(tag);
          tags.push({ el: tag, at: new T.Vector3((box.min.x + box.max.x) / 2, box.max.y, (box.min.z + box.max.z) / 2) });
        }
      });
      var scene = new T.Scene();
      scene.add(gltf.scene);
      var cam3 = new T.PerspectiveCamera(frame.fov_deg, 1, frame.radius / 50, frame.radius * 20);
      var target = new T.Vector3().fromArray(frame.target);
      cam3.position.set(target.x, target.y, target.z + frame.radius);
      var controls = new T.OrbitControls(cam3, renderer.domElement);
      controls.target.copy(target);
      controls.minDistance = frame.radius / 4;
      function layout() {
        var w = stage.clientWidth || 800, h = stage.clientHeight || 440;
        renderer.setPixelRatio(2 * (root.devicePixelRatio || 1));
        renderer.setSize(w, h, true);
        cam3.aspect = w / h;
        cam3.updateProjectionMatrix();
      }
      function render() {
        renderer.setScissorTest(false);
        renderer.clear();
        renderer.render(scene, cam3);
        var w = stage.clientWidth, h = stage.clientHeight;
        tags.forEach(function (t) {
          var p = t.at.clone().project(cam3);
          t.el.style.left = ((p.x + 1) / 2 * w) + 'px';
          t.el.style.top = ((1 - p.y) / 2 * h - 4) + 'px';
          t.el.style.display = p.z < 1 ? '' : 'none';
        });
      }
      controls.addEventListener('change', render);
      if (root.addEventListener) root.addEventListener('resize', function () { layout(); render(); });
      layout();
      controls.update();
      render();
      container.setAttribute('data-viewer', 'ready');
      return { renderer: renderer, camera: cam3, controls: controls };
    }).catch(function (err) {
      stage.appendChild(el('div', { class: 'mv-error' }, 'mvtex viewer: ' + (err && err.message || err)));
      container.setAttribute('data-viewer', 'error');
      console.error(err);
      throw err;
    });
  }

  root.mvtexViewer = { openScene: openScene, openMeshes: openMeshes };
}(typeof self !== 'undefined' ? self : this));
