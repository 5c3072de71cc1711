/* mvtex viewer mathematics: OpenCV cameras in three.js, the novel camera of view weights, and
 * the weights of an eye position. Each function is the browser's copy of a Python function
 * of mvtex, named beside it; the tests run both on the same inputs and compare.
 *
 * Conventions (DESIGN §3, docs/conventions.md): x_cam = R X + t, z forward, y down; pixel
 * (u, v), u right, v down, the centre of the top-left pixel at (0, 0); K = [[fx, s, cx],
 * [0, fy, cy], [0, 0, 1]]. Matrices are arrays of rows; vectors plain arrays.
 *
 * Loads as a classic script (global `mvtexViewMath`) and as a CommonJS module (node).
 */
(function (root, factory) {
  if (typeof module === 'object' && module.exports) module.exports = factory();
  else root.mvtexViewMath = factory();
}(typeof self !== 'undefined' ? self : this, function () {
  'use strict';

  var EPS = 2.220446049250313e-16;

  function matVec(A, x) {
    return A.map(function (row) { return row.reduce(function (s, a, j) { return s + a * x[j]; }, 0); });
  }
  function transpose(A) { return A[0].map(function (_, j) { return A.map(function (row) { return row[j]; }); }); }
  function matMul(A, B) {
    var Bt = transpose(B);
    return A.map(function (row) { return Bt.map(function (col) { return row.reduce(function (s, a, k) { return s + a * col[k]; }, 0); }); });
  }
  function dot(a, b) { return a.reduce(function (s, x, i) { return s + x * b[i]; }, 0); }

  /** Camera centre -R^T t (world, m). */
  function cameraCentre(R, t) {
    return [0, 1, 2].map(function (j) { return -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]); });
  }

  /** Least squares min ||A x - b|| by Householder QR (A: m x n, m >= n, full column rank). */
  function lstsq(A, b) {
    var m = A.length, n = A[0].length;
    var R = A.map(function (row) { return row.slice(); });
    var y = b.slice();
    for (var k = 0; k < n; k++) {
      var norm = 0;
      for (var i = k; i < m; i++) norm += R[i][k] * R[i][k];
      norm = Math.sqrt(norm);
      if (norm === 0) continue;
      var alpha = R[k][k] > 0 ? -norm : norm;
      var v = new Array(m).fill(0);
      for (i = k; i < m; i++) v[i] = R[i][k];
      v[k] -= alpha;
      var vv = 0;
      for (i = k; i < m; i++) vv += v[i] * v[i];
      if (vv === 0) continue;
      for (var j = k; j < n; j++) {
        var s = 0;
        for (i = k; i < m; i++) s += v[i] * R[i][j];
        s = 2 * s / vv;
        for (i = k; i < m; i++) R[i][j] -= s * v[i];
      }
      var sy = 0;
      for (i = k; i < m; i++) sy += v[i] * y[i];
      sy = 2 * sy / vv;
      for (i = k; i < m; i++) y[i] -= sy * v[i];
    }
    var x = new Array(n).fill(0);
    for (k = n - 1; k >= 0; k--) {
      var acc = y[k];
      for (j = k + 1; j < n; j++) acc -= R[k][j] * x[j];
      x[k] = R[k][k] !== 0 ? acc / R[k][k] : 0;
    }
    return x;
  }

  /** Non-negative least squares min ||A x - b||, x >= 0: Lawson and Hanson's active-set
   * method (scipy.optimize.nnls implements the same). A: m x n rows. Returns x (n). */
  function nnls(A, b, maxIter) {
    var m = A.length, n = A[0].length;
    var At = transpose(A);
    var x = new Array(n).fill(0);
    var passive = new Array(n).fill(false);
    var norm1 = 0;
    for (var j = 0; j < n; j++) norm1 = Math.max(norm1, A.reduce(function (s, row) { return s + Math.abs(row[j]); }, 0));
    var tol = 10 * Math.max(m, n) * EPS * norm1;
    var iterations = 0;
    maxIter = maxIter || 3 * n + 50;
    function gradient() {
      var r = b.map(function (bi, i) { return bi - dot(A[i], x); });
      return At.map(function (col) { return dot(col, r); });
    }
    function solvePassive() {
      var idx = [];
      for (var k = 0; k < n; k++) if (passive[k]) idx.push(k);
      var sP = lstsq(A.map(function (row) { return idx.map(function (k) { return row[k]; }); }), b);
      var z = new Array(n).fill(0);
      idx.forEach(function (k, i) { z[k] = sP[i]; });
      return { idx: idx, z: z };
    }
    function independent(j) {  // column j is not (numerically) in the span of the passive columns
      var idx = [];
      for (var k = 0; k < n; k++) if (passive[k]) idx.push(k);
      if (idx.length >= m) return false;
      var col = At[j], norm = Math.sqrt(dot(col, col));
      if (!idx.length) return norm > 0;
      var c = lstsq(A.map(function (row) { return idx.map(function (k) { return row[k]; }); }), col);
      var r = A.map(function (row, i) { return col[i] - idx.reduce(function (s, k, q) { return s + row[k] * c[q]; }, 0); });
      return Math.sqrt(dot(r, r)) > 1e-10 * norm;
    }
    var rejected = new Array(n).fill(false);
    for (;;) {
      var w = gradient();
      var best = -1, wmax = tol;
      for (j = 0; j < n; j++) if (!passive[j] && !rejected[j] && w[j] > wmax) { wmax = w[j]; best = j; }
      if (best < 0) break;
      if (!independent(best)) { rejected[best] = true; continue; }
      passive[best] = true;
      var sol = solvePassive();
      if (!(sol.z[best] > 0)) {  // rounding made the entering column useless: try the next one
        passive[best] = false;
        rejected[best] = true;
        continue;
      }
      rejected.fill(false);
      for (;;) {
        if (++iterations > maxIter) throw new Error('nnls: too many iterations');
        if (sol.idx.every(function (k) { return sol.z[k] > 0; })) { x = sol.z; break; }
        var alpha = Infinity, leaving = -1;
        sol.idx.forEach(function (k) {
          if (sol.z[k] <= 0) {
            var a = x[k] / (x[k] - sol.z[k]);
            if (a < alpha) { alpha = a; leaving = k; }
          }
        });
        for (j = 0; j < n; j++) x[j] += alpha * (sol.z[j] - x[j]);
        x[leaving] = 0;
        sol.idx.forEach(function (k) { if (x[k] <= 0) { passive[k] = false; x[k] = 0; } });
        sol = solvePassive();
      }
    }
    return x;
  }

  var SUM_WEIGHT = 1e3, CONSTRAINT_WEIGHT = 1e4, SPREAD = 1e-3;

  function extent(centres) {
    var e = 0;
    centres.forEach(function (a) {
      centres.forEach(function (c) { e = Math.max(e, (a[0] - c[0]) ** 2 + (a[1] - c[1]) ** 2 + (a[2] - c[2]) ** 2); });
    });
    return Math.max(Math.sqrt(e), 1e-3);
  }

  /** mvtex.views.cameras.nearest_blend_system: A (4 rows), b. */
  function nearestBlendSystem(centres, eye) {
    var L = extent(centres);
    var A = [centres.map(function () { return SUM_WEIGHT; })];
    for (var i = 0; i < 3; i++) A.push(centres.map(function (c) { return (c[i] - eye[i]) / L; }));
    return { A: A, b: [SUM_WEIGHT, 0, 0, 0] };
  }

  /** mvtex.views.cameras.centre_weights_system: A (4+p rows), b. */
  function centreWeightsSystem(centres, point) {
    var L = extent(centres), p = centres.length;
    var A = [centres.map(function () { return CONSTRAINT_WEIGHT; })], b = [CONSTRAINT_WEIGHT, 0, 0, 0];
    for (var i = 0; i < 3; i++) A.push(centres.map(function (c) { return CONSTRAINT_WEIGHT * (c[i] - point[i]) / L; }));
    centres.forEach(function (c, k) {
      var row = new Array(p).fill(0);
      row[k] = Math.sqrt(SPREAD);
      A.push(row);
      var near = ((c[0] - point[0]) ** 2 + (c[1] - point[1]) ** 2 + (c[2] - point[2]) ** 2) / (L * L);
      b.push(-near / (2 * Math.sqrt(SPREAD)));
    });
    return { A: A, b: b };
  }

  /** mvtex.views.cameras.weights_for_centre: weights (p) >= 0 summing to 1. */
  function weightsForCentre(centres, eye) {
    var limit = 50 * centres.length + 100;
    var s1 = nearestBlendSystem(centres, eye);
    var w = nnls(s1.A, s1.b, limit);
    var total = w.reduce(function (s, x) { return s + x; }, 0);
    var nearest = [0, 1, 2].map(function (i) {
      return centres.reduce(function (s, c, k) { return s + (w[k] / total) * c[i]; }, 0);
    });
    var s2 = centreWeightsSystem(centres, nearest);
    w = nnls(s2.A, s2.b, limit);
    total = w.reduce(function (s, x) { return s + x; }, 0);
    return w.map(function (x) { return x / total; });
  }

  // -- rotations as quaternions [w, x, y, z] --------------------------------------------------
  function quatFromMatrix(R) {
    var tr = R[0][0] + R[1][1] + R[2][2], q;
    if (tr > 0) {
      var s = Math.sqrt(tr + 1) * 2;
      q = [0.25 * s, (R[2][1] - R[1][2]) / s, (R[0][2] - R[2][0]) / s, (R[1][0] - R[0][1]) / s];
    } else if (R[0][0] > R[1][1] && R[0][0] > R[2][2]) {
      s = Math.sqrt(1 + R[0][0] - R[1][1] - R[2][2]) * 2;
      q = [(R[2][1] - R[1][2]) / s, 0.25 * s, (R[0][1] + R[1][0]) / s, (R[0][2] + R[2][0]) / s];
    } else if (R[1][1] > R[2][2]) {
      s = Math.sqrt(1 + R[1][1] - R[0][0] - R[2][2]) * 2;
      q = [(R[0][2] - R[2][0]) / s, (R[0][1] + R[1][0]) / s, 0.25 * s, (R[1][2] + R[2][1]) / s];
    } else {
      s = Math.sqrt(1 + R[2][2] - R[0][0] - R[1][1]) * 2;
      q = [(R[1][0] - R[0][1]) / s, (R[0][2] + R[2][0]) / s, (R[1][2] + R[2][1]) / s, 0.25 * s];
    }
    var nq = Math.sqrt(dot(q, q));
    return q.map(function (c) { return c / nq; });
  }
  function matrixFromQuat(q) {
    var n = Math.sqrt(dot(q, q)), w = q[0] / n, x = q[1] / n, y = q[2] / n, z = q[3] / n;
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]];
  }
  /** Slerp from q0 to q1 along the shorter arc (scipy's Slerp), fraction t. */
  function slerp(q0, q1, t) {
    var c = dot(q0, q1);
    if (c < 0) { q1 = q1.map(function (v) { return -v; }); c = -c; }
    if (c > 1 - 1e-15) return q0.map(function (v, i) { return v + t * (q1[i] - v); });
    var theta = Math.acos(Math.min(1, c)), s = Math.sin(theta);
    var a = Math.sin((1 - t) * theta) / s, b = Math.sin(t * theta) / s;
    return q0.map(function (v, i) { return a * v + b * q1[i]; });
  }
  /** Eigenvector of the largest eigenvalue of a symmetric 4x4 matrix (cyclic Jacobi). */
  function topEigenvector(M) {
    var a = M.map(function (r) { return r.slice(); });
    var V = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];
    for (var sweep = 0; sweep < 100; sweep++) {
      var off = 0;
      for (var p = 0; p < 4; p++) for (var q = p + 1; q < 4; q++) off += a[p][q] * a[p][q];
      if (off < 1e-300) break;
      for (p = 0; p < 4; p++) {
        for (q = p + 1; q < 4; q++) {
          if (Math.abs(a[p][q]) < 1e-300) continue;
          var theta = (a[q][q] - a[p][p]) / (2 * a[p][q]);
          var t = (theta >= 0 ? 1 : -1) / (Math.abs(theta) + Math.sqrt(theta * theta + 1));
          var c = 1 / Math.sqrt(t * t + 1), s = t * c;
          for (var k = 0; k < 4; k++) {
            var akp = a[k][p], akq = a[k][q];
            a[k][p] = c * akp - s * akq; a[k][q] = s * akp + c * akq;
          }
          for (k = 0; k < 4; k++) {
            var apk = a[p][k], aqk = a[q][k];
            a[p][k] = c * apk - s * aqk; a[q][k] = s * apk + c * aqk;
          }
          for (k = 0; k < 4; k++) {
            var vkp = V[k][p], vkq = V[k][q];
            V[k][p] = c * vkp - s * vkq; V[k][q] = s * vkp + c * vkq;
          }
        }
      }
    }
    var best = 0;
    for (var i = 1; i < 4; i++) if (a[i][i] > a[best][best]) best = i;
    return V.map(function (row) { return row[best]; });
  }

  /** mvtex.views.cameras.interpolate_camera: the novel camera of `weights` (name -> weight)
   * over `cameras` (name -> {width, height, K, R, t}). */
  function interpolateCamera(cameras, weights) {
    var names = Object.keys(weights);
    var ones = names.filter(function (k) { return weights[k] === 1; });
    if (ones.length === 1 && names.every(function (k) { return k === ones[0] || weights[k] === 0; })) {
      var only = cameras[ones[0]];
      return { width: only.width, height: only.height, K: only.K, R: only.R, t: only.t };
    }
    var used = names.filter(function (k) { return weights[k] > 0; });
    var total = used.reduce(function (s, k) { return s + weights[k]; }, 0);
    var w = used.map(function (k) { return weights[k] / total; });
    var cams = used.map(function (k) { return cameras[k]; });
    var centre = [0, 0, 0], K = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
    cams.forEach(function (c, i) {
      var ci = cameraCentre(c.R, c.t);
      for (var a = 0; a < 3; a++) {
        centre[a] += w[i] * ci[a];
        for (var b = 0; b < 3; b++) K[a][b] += w[i] * c.K[a][b];
      }
    });
    K[1][0] = 0; K[2] = [0, 0, 1];
    var R;
    if (cams.length === 2) {
      R = matrixFromQuat(slerp(quatFromMatrix(cams[0].R), quatFromMatrix(cams[1].R), w[1]));
    } else {
      var M = [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]];
      cams.forEach(function (c, i) {
        var q = quatFromMatrix(c.R);
        for (var a = 0; a < 4; a++) for (var b = 0; b < 4; b++) M[a][b] += w[i] * q[a] * q[b];
      });
      R = matrixFromQuat(topEigenvector(M));
    }
    var t = matVec(R, centre).map(function (v) { return -v; });
    return { width: cams[0].width, height: cams[0].height, K: K, R: R, t: t };
  }

  /** mvtex.views.preview.eye_cameras: the left and right eyes, the viewpoint moved by -/+ ipd/2
   * along its x axis (image right). */
  function eyeCameras(viewpoint, ipd) {
    var centre = cameraCentre(viewpoint.R, viewpoint.t);
    return [-1, 1].map(function (sign) {
      var c = centre.map(function (v, a) { return v + sign * 0.5 * ipd * viewpoint.R[0][a]; });
      return { width: viewpoint.width, height: viewpoint.height, K: viewpoint.K, R: viewpoint.R,
               t: matVec(viewpoint.R, c).map(function (v) { return -v; }) };
    });
  }

  /** The GL projection of an OpenCV camera for a camera looking down -z with y up (three.js),
   * as mvtex.render.raster.clip_from_camera maps pixel (u, v) to window (u + 0.5, H - v - 0.5):
   * the canvas shows the OpenCV image, row 0 at the top. Rows of the 4x4 matrix. */
  function projectionFromK(K, width, height, near, far) {
    var fx = K[0][0], s = K[0][1], cx = K[0][2], fy = K[1][1], cy = K[1][2];
    return [[2 * fx / width, -2 * s / width, 1 - (2 * cx + 1) / width, 0],
            [0, 2 * fy / height, (2 * cy + 1) / height - 1, 0],
            [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
            [0, 0, -1, 0]];
  }

  /** The world-from-camera matrix (rows) of a camera looking down -z with y up that sees what
   * the OpenCV camera (R, t) sees: GL camera axes = diag(1, -1, -1) OpenCV axes. */
  function worldFromGLCamera(R, t) {
    var c = cameraCentre(R, t);
    // columns: x_cam, -y_cam, -z_cam in world coordinates (rows of R)
    return [[R[0][0], -R[1][0], -R[2][0], c[0]],
            [R[0][1], -R[1][1], -R[2][1], c[1]],
            [R[0][2], -R[1][2], -R[2][2], c[2]],
            [0, 0, 0, 1]];
  }

  /** (R, t) of the OpenCV camera a world-from-GL-camera matrix (rows) describes. */
  function openCVFromWorldGL(M) {
    var R = [[M[0][0], M[1][0], M[2][0]], [-M[0][1], -M[1][1], -M[2][1]], [-M[0][2], -M[1][2], -M[2][2]]];
    var c = [M[0][3], M[1][3], M[2][3]];
    return { R: R, t: matVec(R, c).map(function (v) { return -v; }) };
  }

  /** Rodrigues: rotation vector <-> matrix (cv2.Rodrigues). */
  function rodriguesToMatrix(r) {
    var theta = Math.sqrt(dot(r, r));
    if (theta < 1e-300) return [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
    var h = Math.sin(theta / 2) / theta;
    return matrixFromQuat([Math.cos(theta / 2), r[0] * h, r[1] * h, r[2] * h]);
  }
  function matrixToRodrigues(R) {
    var q = quatFromMatrix(R);
    if (q[0] < 0) q = q.map(function (v) { return -v; });
    var s = Math.sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (s < 1e-300) return [0, 0, 0];
    var theta = 2 * Math.atan2(s, q[0]);
    return [q[1] / s * theta, q[2] / s * theta, q[3] / s * theta];
  }

  /** Parse "A=0.5,B=0.5" (mvtex.views.cameras.parse_weights) or a camera name; checks as
   * check_weights: known names, finite, >= 0, summing to 1 (within 1e-6). */
  function parseView(text, names) {
    text = String(text).trim();
    if (names.indexOf(text) >= 0) { var one = {}; one[text] = 1; return one; }
    var weights = {};
    text.split(',').forEach(function (item) {
      item = item.trim();
      if (!item) return;
      var at = item.indexOf('=');
      var name = at > 0 ? item.slice(0, at).trim() : '', value = at > 0 ? Number(item.slice(at + 1)) : NaN;
      if (!name || !isFinite(value)) throw new Error('view: ' + JSON.stringify(item) + ' is not NAME=NUMBER');
      if (names.indexOf(name) < 0) throw new Error('view: no camera ' + JSON.stringify(name) + ' (cameras: ' + names.join(', ') + ')');
      if (value < 0) throw new Error('view: weights must be >= 0');
      weights[name] = value;
    });
    var total = Object.keys(weights).reduce(function (s, k) { return s + weights[k]; }, 0);
    if (!Object.keys(weights).length || Math.abs(total - 1) > 1e-6) throw new Error('view: weights must sum to 1, they sum to ' + total);
    return weights;
  }

  /** "W,H,fx,fy,cx,cy,rx,ry,rz,tx,ty,tz" <-> an OpenCV camera (rotation as a Rodrigues vector). */
  function parseCamera(text) {
    var v = String(text).split(',').map(Number);
    if (v.length !== 12 || !v.every(isFinite) || !(v[0] >= 1 && v[1] >= 1 && v[2] > 0 && v[3] > 0)) {
      throw new Error('camera: expected W,H,fx,fy,cx,cy,rx,ry,rz,tx,ty,tz (12 numbers)');
    }
    return { width: Math.round(v[0]), height: Math.round(v[1]), K: [[v[2], 0, v[4]], [0, v[3], v[5]], [0, 0, 1]],
             R: rodriguesToMatrix(v.slice(6, 9)), t: v.slice(9, 12) };
  }
  function formatCamera(cam) {
    var r = matrixToRodrigues(cam.R);
    var nums = [cam.K[0][0], cam.K[1][1], cam.K[0][2], cam.K[1][2]].concat(r, cam.t);
    return [cam.width, cam.height].concat(nums.map(function (x) { return +x.toPrecision(10); })).join(',');
  }

  return {
    nnls: nnls, lstsq: lstsq, nearestBlendSystem: nearestBlendSystem, centreWeightsSystem: centreWeightsSystem, weightsForCentre: weightsForCentre,
    interpolateCamera: interpolateCamera, eyeCameras: eyeCameras, cameraCentre: cameraCentre,
    projectionFromK: projectionFromK, worldFromGLCamera: worldFromGLCamera, openCVFromWorldGL: openCVFromWorldGL,
    quatFromMatrix: quatFromMatrix, matrixFromQuat: matrixFromQuat, rodriguesToMatrix: rodriguesToMatrix,
    matrixToRodrigues: matrixToRodrigues, parseView: parseView, parseCamera: parseCamera, formatCamera: formatCamera,
    matMul: matMul, matVec: matVec, transpose: transpose
  };
}));
