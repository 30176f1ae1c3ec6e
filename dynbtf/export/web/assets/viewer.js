// dynbtf web viewer: loads an export written by `dynbtf export --format web` and renders it with
// WebGL2. No build step, no network: every file is read through a <script> tag, which browsers
// allow for pages opened from disk. `DynBTF.load`, `DynBTF.Renderer` and `DynBTF.origin` are also
// what other pages (and dynbtf's browser tests) use to run the same shader.
(function () {
  'use strict';
  var DynBTF = window.DynBTF = window.DynBTF || {};
  var pending = {manifest: null, shader: null, files: {}};

  // ------------------------------------------------------------------ loading
  DynBTF.manifest = function (manifest, shader) { pending.manifest = manifest; pending.shader = shader; };
  DynBTF.file = function (name, bytes, base64) { pending.files[name] = {bytes: bytes, base64: base64}; };

  function loadScript(src) {
    return new Promise(function (resolve, reject) {
      var s = document.createElement('script');
      s.src = src;
      s.onload = function () { resolve(); };
      s.onerror = function () { reject(new Error(src + ': missing or unreadable (could not load the file)')); };
      document.head.appendChild(s);
    });
  }

  function decodeBase64(name, entry, expected) {
    var text;
    try { text = atob(entry.base64); } catch (e) { throw new Error(name + ': unreadable (its data is not valid base64)'); }
    if (text.length !== entry.bytes || text.length !== expected) {
      throw new Error(name + ': unreadable (holds ' + text.length + ' bytes, the manifest expects ' + expected + ')');
    }
    var out = new Uint8Array(text.length);
    for (var i = 0; i < text.length; ++i) out[i] = text.charCodeAt(i);
    return out.buffer;
  }

  // The export whose scripts have run: {manifest, shader, files: {name: ArrayBuffer}} (throws naming a bad file).
  DynBTF.collect = function () {
    var m = pending.manifest;
    if (!m || m.format !== 'dynbtf-web') throw new Error('manifest.js: unreadable (it defines no dynbtf web export)');
    if (m.version !== 1) throw new Error('manifest.js: export format version ' + m.version + ' is not supported (expected 1)');
    var files = {};
    Object.keys(m.files).forEach(function (n) {
      var entry = pending.files[n];
      if (!entry) throw new Error(n + '.js: missing or unreadable (it defines no data for ' + n + ')');
      files[n] = decodeBase64(n + '.js', entry, m.files[n].bytes);
    });
    return {manifest: m, shader: pending.shader, files: files};
  };

  // Load manifest.js and every file's .js twin from `base` (a directory URL ending in '/', or '').
  DynBTF.load = function (base) {
    base = base || '';
    pending.manifest = null;
    return loadScript(base + 'manifest.js').then(function () {
      var m = pending.manifest;
      if (!m || m.format !== 'dynbtf-web') throw new Error('manifest.js: unreadable (it defines no dynbtf web export)');
      return Promise.all(Object.keys(m.files).map(function (n) { return loadScript(base + n + '.js'); }));
    }).then(function () { return DynBTF.collect(); });
  };

  // ------------------------------------------------------------------ the repeat origin (float64 on the CPU)
  // dynbtf.export.web.shader.repeat_origin: the same float64 and (BigInt) int64 operations as the library.
  function scaledInteger(lat, i) {
    if (Math.abs(i) < 134217728) {  // 2^27: two-term float64 product
      var p = i * lat.scale_hi, whole = Math.floor(p);
      var frac = (p - whole) + i * lat.scale_lo, carry = Math.floor(frac);
      return {whole: BigInt(whole) + BigInt(carry), frac: frac - carry};
    }
    var I = BigInt(i), a = I >> 26n, b = I & ((1n << 26n) - 1n);
    var n1 = BigInt(lat.n1), n2 = BigInt(lat.n2);
    var pb1 = b * n1, pa2 = a * n2, pb2 = b * n2;
    var w = 4n * a * n1 + (pb1 >> 24n) + (pa2 >> 24n) + (pb2 >> 50n);
    var m24 = (1n << 24n) - 1n, m50 = (1n << 50n) - 1n;
    var f = Number((pb1 & m24) + (pa2 & m24)) * Math.pow(2, -24) + Number(pb2 & m50) * Math.pow(2, -50) + i * lat.c3;
    var c = Math.floor(f);
    return {whole: w + BigInt(c), frac: f - c};
  }

  function mod(a, n) { var r = a % n; return r < 0 ? r + n : r; }
  function words(x) { var u = BigInt.asUintN(64, x); return [Number(u & 0xFFFFFFFFn), Number(u >> 32n)]; }

  // The exported method a name stands for: 'auto' is the model's choice (manifest.auto.method).
  DynBTF.methodName = function (m, name) { return name === 'auto' && m.auto ? m.auto.method : name; };

  // Split a position (pu, pv) in exemplar repeats for method entry `method` of manifest `m`.
  // `lattice` holds the int64 lattice vertex of the repeat; for struct (an entry with cells) the int64
  // index of the repeat's first cell, I x cells (the library's cell index is I n + column).
  DynBTF.origin = function (m, method, pu, pv) {
    var lat = m.lattice;
    if (!(Math.abs(pu) < lat.max_repeats && Math.abs(pv) < lat.max_repeats)) {
      throw new Error('uv x scale must be below 2^52 exemplar repeats, got (' + pu + ', ' + pv + ')');
    }
    var wu = Math.floor(pu), fu = pu - wu, wv = Math.floor(pv), fv = pv - wv;
    if (fu >= 1) { fu -= 1; wu += 1; }
    if (fv >= 1) { fv -= 1; wv += 1; }
    var s = scaledInteger(lat, wu);
    var x = words(s.whole - 2n * BigInt(wv)), y = words(4n * BigInt(wv));
    var e = m.methods[DynBTF.methodName(m, method)];
    if (!e) throw new Error('method ' + method + ' is not in this export (it has ' + Object.keys(m.methods).join(', ') + ')');
    var pw = e.plane.width, ph = e.plane.height;
    if (e.cells) { x = words(BigInt(wu) * BigInt(e.cells[0])); y = words(BigInt(wv) * BigInt(e.cells[1])); }
    return {lattice: [x[0], x[1], y[0], y[1]], phase: s.frac,
            texel: [mod(mod(wu, pw) * (e.density[0] % pw), pw), mod(mod(wv, ph) * (e.density[1] % ph), ph)],
            fraction: [fu, fv]};
  };

  // ------------------------------------------------------------------ GL resources
  var FORMATS = {
    RGBA32F: ['RGBA32F', 'RGBA', 'FLOAT', Float32Array], RGBA16F: ['RGBA16F', 'RGBA', 'HALF_FLOAT', Uint16Array],
    RGBA8: ['RGBA8', 'RGBA', 'UNSIGNED_BYTE', Uint8Array], R32F: ['R32F', 'RED', 'FLOAT', Float32Array],
    R16F: ['R16F', 'RED', 'HALF_FLOAT', Uint16Array], R8: ['R8', 'RED', 'UNSIGNED_BYTE', Uint8Array],
    R16I: ['R16I', 'RED_INTEGER', 'SHORT', Int16Array]
  };
  // texture units of the export's samplers (5..9 are left to the caller, e.g. dynbtf's query pages)
  var UNITS = {plane: 0, lut: 1, lum: 2, fh: 3, fd: 4, cells: 10};

  function texture(gl, entry, buffer) {
    var f = FORMATS[entry.format];
    if (!f) throw new Error(entry.file + ': unknown texture format ' + entry.format);
    var data = new f[3](buffer);
    var layered = entry.layers !== undefined;
    var target = layered ? gl.TEXTURE_2D_ARRAY : gl.TEXTURE_2D;
    var t = gl.createTexture();
    gl.bindTexture(target, t);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    var max = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    if (entry.width > max || entry.height > max) {
      throw new Error(entry.file + ': ' + entry.width + 'x' + entry.height + ' texels exceed this GPU\'s limit of ' + max);
    }
    if (layered) {
      gl.texImage3D(target, 0, gl[f[0]], entry.width, entry.height, entry.layers, 0, gl[f[1]], gl[f[2]], data);
    } else {
      gl.texImage2D(target, 0, gl[f[0]], entry.width, entry.height, 0, gl[f[1]], gl[f[2]], data);
    }
    gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(target, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(target, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return t;
  }

  function ubo(gl, buffer, offsetFloats, floats) {
    var b = gl.createBuffer();
    gl.bindBuffer(gl.UNIFORM_BUFFER, b);
    gl.bufferData(gl.UNIFORM_BUFFER, new Float32Array(buffer, offsetFloats * 4, floats), gl.STATIC_DRAW);
    return b;
  }

  function compile(gl, type, source, what) {
    var s = gl.createShader(type);
    gl.shaderSource(s, source);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
      throw new Error(what + ' does not compile: ' + gl.getShaderInfoLog(s));
    }
    return s;
  }

  DynBTF.FRAGMENT_HEADER = '#version 300 es\nprecision highp float;\nprecision highp int;\n' +
    'precision highp sampler2DArray;\nprecision highp usampler2D;\nprecision highp isampler2D;\n';

  // A renderer: the export's textures and weights on `gl`, and programs built on dynbtf.glsl.
  DynBTF.Renderer = function (gl, data) {
    var m = data.manifest, self = this;
    this.gl = gl;
    this.manifest = m;
    this.shader = data.shader;
    this.angular = {fh: texture(gl, m.angular.f_H, data.files[m.angular.f_H.file]),
                    fd: texture(gl, m.angular.f_D, data.files[m.angular.f_D.file])};
    this.methods = {};
    Object.keys(m.methods).forEach(function (name) {
      var e = m.methods[name], r = {entry: e};
      r.plane = texture(gl, e.plane, data.files[e.plane.file]);
      if (e.lut) r.lut = texture(gl, e.lut, data.files[e.lut.file]);
      if (e.luminance) r.lum = texture(gl, e.luminance, data.files[e.luminance.file]);
      if (e.tables) r.cells = texture(gl, e.tables, data.files[e.tables.file]);
      r.layer1 = ubo(gl, data.files[e.layer1.file], 0, e.layer1.floats);
      self.methods[name] = r;
    });
    // 1x1 stand-ins for the samplers a method does not use (every sampler gets a texture of its type)
    var zero = {width: 1, height: 1, format: 'R32F', file: '(stand-in)'};
    this.dummy2d = texture(gl, zero, new Float32Array(1).buffer);
    this.dummyInt = texture(gl, {width: 1, height: 1, format: 'R16I', file: '(stand-in)'}, new Int16Array(1).buffer);
  };

  // Compile `main` (GLSL declaring its outputs and main()) after dynbtf.glsl; `vertex` defaults to a full-screen triangle.
  DynBTF.Renderer.prototype.program = function (main, vertex) {
    var gl = this.gl;
    vertex = vertex || '#version 300 es\nvoid main() { vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);' +
      ' gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0); }\n';
    var p = gl.createProgram();
    gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vertex, 'the vertex shader'));
    gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, DynBTF.FRAGMENT_HEADER + this.shader + '\n' + main,
                               'the fragment shader (dynbtf.glsl)'));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error('the shader does not link: ' + gl.getProgramInfoLog(p));
    var index = gl.getUniformBlockIndex(p, 'DynbtfLayer1');  // the method's layer 1 (the rest are constants)
    if (index !== gl.INVALID_INDEX) gl.uniformBlockBinding(p, index, 0);
    return p;
  };

  // Make `program` current with method `name`'s textures, tables and uniforms ('auto': the model's choice).
  DynBTF.Renderer.prototype.use = function (program, name) {
    var gl = this.gl, r = this.methods[DynBTF.methodName(this.manifest, name)];
    if (!r) throw new Error('method ' + name + ' is not in this export (it has ' + Object.keys(this.methods).join(', ') + ')');
    var e = r.entry;
    gl.useProgram(program);
    function u(n) { return gl.getUniformLocation(program, n); }
    function bind(unit, target, t, sampler) {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(target, t);
      gl.uniform1i(u(sampler), unit);
    }
    bind(UNITS.plane, gl.TEXTURE_2D_ARRAY, r.plane, 'dynbtf_plane');
    bind(UNITS.lut, gl.TEXTURE_2D, r.lut || this.dummy2d, 'dynbtf_lut');
    bind(UNITS.lum, gl.TEXTURE_2D, r.lum || this.dummy2d, 'dynbtf_lum');
    bind(UNITS.fh, gl.TEXTURE_2D_ARRAY, this.angular.fh, 'dynbtf_fh');
    bind(UNITS.fd, gl.TEXTURE_2D_ARRAY, this.angular.fd, 'dynbtf_fd');
    bind(UNITS.cells, gl.TEXTURE_2D, r.cells || this.dummyInt, 'dynbtf_cells');
    gl.uniform1i(u('dynbtf_mode'), e.mode);
    gl.uniform2i(u('dynbtf_plane_size'), e.plane.width, e.plane.height);
    gl.uniform2i(u('dynbtf_density'), e.density[0], e.density[1]);
    gl.uniform1ui(u('dynbtf_seed_state'), e.seed_state);
    gl.uniform1f(u('dynbtf_gamma'), e.gamma || 1.0);
    gl.uniform1f(u('dynbtf_beta'), e.beta || 0.0);
    gl.uniform1f(u('dynbtf_gain_k'), e.gain_k || 1.0);
    gl.uniform1f(u('dynbtf_g_min'), e.g_min || 0.0);
    gl.uniform1f(u('dynbtf_inv_step'), e.inv_step || 1.0);
    gl.uniform1i(u('dynbtf_lut_size'), e.lut ? e.lut.size : 2);
    gl.uniform1i(u('dynbtf_lut_row'), e.lut ? e.lut.row : 2);
    var t = e.tables;  // struct: cells, cut bands, offsets and where each table starts in the texture
    gl.uniform2i(u('dynbtf_cell_grid'), t ? e.cells[0] : 1, t ? e.cells[1] : 1);
    gl.uniform2i(u('dynbtf_cell_margin'), t ? e.margin[0] : 0, t ? e.margin[1] : 0);
    gl.uniform1i(u('dynbtf_cell_count'), t ? e.count : 1);
    gl.uniform1i(u('dynbtf_cell_row'), t ? t.row : 1);
    gl.uniform2i(u('dynbtf_cut_start'), t ? t.vertical_cuts.start : 0, t ? t.horizontal_cuts.start : 0);
    var ones = e.plane.scale.map(function () { return 1.0; }), zeros = e.plane.scale.map(function () { return 0.0; });
    gl.uniform4fv(u('dynbtf_plane_scale'), e.plane.scale);
    gl.uniform4fv(u('dynbtf_plane_bias'), e.plane.bias);
    gl.uniform4fv(u('dynbtf_lut_scale'), e.lut ? e.lut.scale : ones);
    gl.uniform4fv(u('dynbtf_lut_bias'), e.lut ? e.lut.bias : zeros);
    gl.uniform4f(u('dynbtf_lum_scale_bias'), e.luminance ? e.luminance.scale : 1.0, e.luminance ? e.luminance.bias : 0.0, 0, 0);
    var a = this.manifest.angular;
    gl.uniform4fv(u('dynbtf_fh_scale'), a.f_H.scale);
    gl.uniform4fv(u('dynbtf_fh_bias'), a.f_H.bias);
    gl.uniform4fv(u('dynbtf_fd_scale'), a.f_D.scale);
    gl.uniform4fv(u('dynbtf_fd_bias'), a.f_D.bias);
    if (e.height) {  // relief models: the height channel in terms of the latent features
      gl.uniform4fv(u('dynbtf_height_map'), e.height.map);
      gl.uniform1f(u('dynbtf_height_offset'), e.height.offset);
    }
    gl.bindBufferBase(gl.UNIFORM_BUFFER, 0, r.layer1);
  };

  // ------------------------------------------------------------------ the viewer page
  var VERTEX = [
    '#version 300 es',
    'in vec3 a_position; in vec3 a_normal; in vec3 a_tangent; in vec2 a_uv;',
    'uniform mat4 u_view_projection; uniform vec2 u_local_origin; uniform float u_scale;',
    'out vec3 v_position; out vec3 v_normal; out vec3 v_tangent; out vec2 v_local;',
    'void main() {',
    '  v_position = a_position; v_normal = a_normal; v_tangent = a_tangent;',
    '  v_local = u_local_origin + a_uv * u_scale;',  // exemplar repeats from the origin (float32)
    '  gl_Position = u_view_projection * vec4(a_position, 1.0);',
    '}'].join('\n');
  var SHADE = [
    'in vec3 v_position; in vec3 v_normal; in vec3 v_tangent; in vec2 v_local;',
    'uniform uvec4 u_lattice; uniform float u_phase; uniform ivec2 u_texel;',
    'uniform vec3 u_camera; uniform vec3 u_light; uniform float u_intensity;',
    'out vec4 color;',
    'vec3 srgb(vec3 c) { c = clamp(c, 0.0, 1.0);',
    '  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c)); }',
    'void main() {',
    '  vec3 n = normalize(v_normal);',
    '  vec3 t = normalize(v_tangent - dot(v_tangent, n) * n);',
    '  vec3 b = cross(n, t);',  // (t, b, n) right-handed: x along +u, y along +v, z = normal
    '  vec3 wv = normalize(u_camera - v_position);',
    '  vec3 wv_local = vec3(dot(wv, t), dot(wv, b), dot(wv, n));',
    '  vec3 wl_local = vec3(dot(u_light, t), dot(u_light, b), dot(u_light, n));',
    '  DynbtfOrigin o; o.lattice = u_lattice; o.phase = u_phase; o.texel = u_texel;',
    '  vec3 value = dynbtf_eval(o, v_local, wv_local, wl_local);',  // pi f_r, excluding the cosine
    '  vec3 radiance = value * max(wl_local.z, 0.0) * u_intensity;',
    '  color = vec4(srgb(radiance), 1.0);',
    '}'].join('\n');

  function plane() {  // z = 0, x and y in [-1, 1]; u along +x, v along +y, normal +z
    var p = [], n = [], t = [], uv = [], idx = [];
    [[0, 0], [1, 0], [1, 1], [0, 1]].forEach(function (c) {
      p.push(2 * c[0] - 1, 2 * c[1] - 1, 0); n.push(0, 0, 1); t.push(1, 0, 0); uv.push(c[0], c[1]);
    });
    idx.push(0, 1, 2, 0, 2, 3);
    return {position: p, normal: n, tangent: t, uv: uv, index: idx};
  }

  function sphere(rows, cols) {  // unit sphere, pole on +z; u = phi / 2 pi, v = 1 - theta / pi (right-handed)
    var p = [], n = [], t = [], uv = [], idx = [];
    for (var i = 0; i <= rows; ++i) {
      var th = Math.PI * i / rows;
      for (var j = 0; j <= cols; ++j) {
        var ph = 2 * Math.PI * j / cols;
        var x = Math.sin(th) * Math.cos(ph), y = Math.sin(th) * Math.sin(ph), z = Math.cos(th);
        p.push(x, y, z); n.push(x, y, z); t.push(-Math.sin(ph), Math.cos(ph), 0); uv.push(j / cols, 1 - i / rows);
      }
    }
    for (i = 0; i < rows; ++i) {
      for (j = 0; j < cols; ++j) {
        var a = i * (cols + 1) + j, b = a + cols + 1;
        idx.push(a, b, a + 1, a + 1, b, b + 1);
      }
    }
    return {position: p, normal: n, tangent: t, uv: uv, index: idx};
  }

  function direction(thetaDeg, phiDeg) {
    var t = thetaDeg * Math.PI / 180, p = phiDeg * Math.PI / 180;
    return [Math.sin(t) * Math.cos(p), Math.sin(t) * Math.sin(p), Math.cos(t)];
  }

  function lookAt(eye, up) {  // view matrix looking at the origin (column-major)
    var f = eye.map(function (v) { return -v; }), lf = Math.hypot(f[0], f[1], f[2]);
    f = f.map(function (v) { return v / lf; });
    var s = [f[1] * up[2] - f[2] * up[1], f[2] * up[0] - f[0] * up[2], f[0] * up[1] - f[1] * up[0]];
    var ls = Math.hypot(s[0], s[1], s[2]) || 1;
    s = s.map(function (v) { return v / ls; });
    var u = [s[1] * f[2] - s[2] * f[1], s[2] * f[0] - s[0] * f[2], s[0] * f[1] - s[1] * f[0]];
    function d(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
    return [s[0], u[0], -f[0], 0, s[1], u[1], -f[1], 0, s[2], u[2], -f[2], 0, -d(s, eye), -d(u, eye), d(f, eye), 1];
  }

  function perspective(fovy, aspect, near, far) {
    var f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0];
  }

  function multiply(a, b) {
    var o = new Array(16);
    for (var c = 0; c < 4; ++c) {
      for (var r = 0; r < 4; ++r) {
        var s = 0;
        for (var k = 0; k < 4; ++k) s += a[k * 4 + r] * b[c * 4 + k];
        o[c * 4 + r] = s;
      }
    }
    return o;
  }

  function mesh(gl, program, geometry) {
    var vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    [['a_position', geometry.position, 3], ['a_normal', geometry.normal, 3], ['a_tangent', geometry.tangent, 3],
     ['a_uv', geometry.uv, 2]].forEach(function (a) {
      var loc = gl.getAttribLocation(program, a[0]);
      if (loc < 0) return;
      var b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(a[1]), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, a[2], gl.FLOAT, false, 0, 0);
    });
    var ib = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, new Uint32Array(geometry.index), gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    return {vao: vao, count: geometry.index.length};
  }

  function showError(message) {
    var box = document.getElementById('dynbtf-error');
    if (!box) return;
    box.textContent = message;
    box.hidden = false;
    document.body.setAttribute('data-state', 'error');
  }
  DynBTF.showError = showError;

  function startViewer(canvas) {
    var gl = canvas.getContext('webgl2', {antialias: false});
    if (!gl) { showError('This browser has no WebGL2: the viewer needs it.'); return; }
    DynBTF.load('').then(function (data) {
      var renderer = new DynBTF.Renderer(gl, data), m = data.manifest;
      var program = renderer.program(SHADE, VERTEX);
      var meshes = {plane: mesh(gl, program, plane()), sphere: mesh(gl, program, sphere(96, 192))};
      var ui = {};
      ['shape', 'method', 'scale', 'origin', 'view-theta', 'view-phi', 'distance', 'light-theta', 'light-phi',
       'intensity', 'resolution'].forEach(function (id) { ui[id] = document.getElementById(id); });
      Object.keys(m.methods).forEach(function (name) {
        var o = document.createElement('option');
        o.value = name;
        o.textContent = m.auto && m.auto.method === name ? name + ' (auto)' : name;
        if (m.auto && m.auto.method === name) o.title = m.auto.line;
        ui.method.appendChild(o);
      });
      ui.method.value = m.default_method;
      // the slider reaches the exported scale (up to twice it, at least 64; down to it if below 1), within what
      // the shader's local uv spans
      var localRepeats = (m.lattice && m.lattice.local_repeats) || 4096;
      ui.scale.max = Math.min(localRepeats, Math.max(64, Math.ceil(2 * m.scale)));
      ui.scale.min = Math.min(1, m.scale);
      if (m.scale !== Math.round(m.scale)) ui.scale.step = 'any';  // a fractional scale is kept, not rounded
      ui.scale.value = m.scale;
      // initial settings from the address: index.html?shape=sphere&method=hex&origin=1e6&light-theta=60 ...
      new URLSearchParams(window.location.search).forEach(function (v, k) {
        if (!ui[k]) throw new Error('unknown page parameter ' + k + ' (expected one of ' + Object.keys(ui).join(', ') + ')');
        if (k === 'method') v = DynBTF.methodName(m, v);  // method=auto: the model's choice
        ui[k].value = v;
        if (ui[k].value !== v && ui[k].tagName === 'SELECT') throw new Error('page parameter ' + k + '=' + v + ' is not one of its choices');
      });
      var debug = gl.getExtension('WEBGL_debug_renderer_info');
      var glName = debug ? gl.getParameter(debug.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
      var software = /SwiftShader|llvmpipe|Software/.test(glName);
      if (software && !new URLSearchParams(window.location.search).has('resolution')) {
        ui.resolution.value = '0.25';  // software GL: a few frames per second at most
      }
      document.getElementById('info').textContent = m.kind + ' model' + (m.source ? ' ' + m.source : '') + ', ' +
        m.precision + ' textures, ' + Object.keys(m.methods).length + ' method(s)' +
        (m.auto ? ' (' + m.auto.line + ')' : '') + '; ' +
        m.channels + ' positional channels, decoder ' + m.layers + ' x ' + m.hidden + '. GL: ' + glName +
        (software ? ' (software GL: a few frames per second at most)' : '');
      function value(id) {
        var v = parseFloat(ui[id].value);
        var out = document.getElementById(id + '-value');
        if (out) out.textContent = ui[id].value;
        return v;
      }
      // orbit: drag to turn the camera, wheel to move it closer
      var drag = null;
      canvas.addEventListener('mousedown', function (e) { drag = [e.clientX, e.clientY]; });
      window.addEventListener('mouseup', function () { drag = null; });
      window.addEventListener('mousemove', function (e) {
        if (!drag) return;
        var t = Math.min(89, Math.max(0, value('view-theta') - (e.clientY - drag[1]) * 0.3));
        var p = ((value('view-phi') - (e.clientX - drag[0]) * 0.3) % 360 + 360) % 360;
        ui['view-theta'].value = t; ui['view-phi'].value = p;
        drag = [e.clientX, e.clientY];
      });
      canvas.addEventListener('wheel', function (e) {
        e.preventDefault();
        ui.distance.value = Math.min(12, Math.max(1.5, value('distance') * (e.deltaY > 0 ? 1.1 : 0.9)));
      }, {passive: false});
      var frames = -1, last = 0, drawn = 0, frameError = false, fps = document.getElementById('fps');  // counted from the first frame's start
      function frame(now) {
        try {
          var method = ui.method.value, scale = value('scale'), origin = Number(ui.origin.value.trim() || '0');
          if (!isFinite(origin)) throw new Error('uv origin: expected a number such as 0 or 1e6, got ' + ui.origin.value);
          var o = DynBTF.origin(m, method, origin * scale, origin * scale);
          renderer.use(program, method);
          var factor = parseFloat(ui.resolution.value) || 1;
          var w = Math.max(1, Math.round(canvas.clientWidth * factor)), h = Math.max(1, Math.round(canvas.clientHeight * factor));
          if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
          gl.viewport(0, 0, canvas.width, canvas.height);
          gl.clearColor(0.08, 0.08, 0.09, 1);
          gl.enable(gl.DEPTH_TEST);
          gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
          var eye = direction(value('view-theta'), value('view-phi')).map(function (v) { return v * value('distance'); });
          var up = value('view-theta') < 1e-3 ? [0, 1, 0] : [0, 0, 1];
          var vp = multiply(perspective(0.7, canvas.width / Math.max(canvas.height, 1), 0.05, 50), lookAt(eye, up));
          function u(n) { return gl.getUniformLocation(program, n); }
          gl.uniformMatrix4fv(u('u_view_projection'), false, vp);
          gl.uniform2f(u('u_local_origin'), o.fraction[0], o.fraction[1]);
          gl.uniform1f(u('u_scale'), scale);
          gl.uniform4ui(u('u_lattice'), o.lattice[0], o.lattice[1], o.lattice[2], o.lattice[3]);
          gl.uniform1f(u('u_phase'), o.phase);
          gl.uniform2i(u('u_texel'), o.texel[0], o.texel[1]);
          gl.uniform3fv(u('u_camera'), eye);
          gl.uniform3fv(u('u_light'), direction(value('light-theta'), value('light-phi')));
          gl.uniform1f(u('u_intensity'), value('intensity'));
          var shape = meshes[ui.shape.value];
          gl.bindVertexArray(shape.vao);
          gl.drawElements(gl.TRIANGLES, shape.count, gl.UNSIGNED_INT, 0);
          gl.bindVertexArray(null);
        } catch (err) {  // e.g. a uv origin beyond 2^52 repeats: say so, and draw again once it is fixed
          showError(String(err.message || err));
          frameError = true;
          window.requestAnimationFrame(frame);
          return;
        }
        if (frameError) {
          document.getElementById('dynbtf-error').hidden = true;
          frameError = false;
        }
        frames += 1;
        if (frames === 0) {
          last = now;
        } else if (now - last >= 1000 || (frames === 1 && fps.textContent === '-')) {  // after 2 frames, then every second
          var span = Math.max(now - last, 0.1);
          fps.textContent = (frames * 1000 / span).toFixed(1) + ' fps, ' + (span / frames).toFixed(1) +
            ' ms per frame at ' + canvas.width + 'x' + canvas.height;
          frames = 0;
          last = now;
        }
        drawn += 1;
        document.body.setAttribute('data-state', 'running');
        document.body.setAttribute('data-frames', String(drawn));
        window.requestAnimationFrame(frame);
      }
      window.requestAnimationFrame(frame);
    }).catch(function (err) { showError(String(err.message || err)); });
  }

  DynBTF.startViewer = startViewer;
  if (document.currentScript && document.currentScript.hasAttribute('data-viewer')) {
    window.addEventListener('load', function () { startViewer(document.getElementById('view')); });
  }
})();
