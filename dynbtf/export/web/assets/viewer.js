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
  // index of the repeat's first cell, I x cells (the library's cell index is I n + column). `element`: for an
  // entry whose elements vary, the repeat's first element (I_u columns - I_v shift, I_v rows), int64 words.
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
    var g = e.elements, ex = [0, 0], ey = [0, 0];
    if (g) { ex = words(BigInt(wu) * BigInt(g.columns) - BigInt(wv) * BigInt(g.shift)); ey = words(BigInt(wv) * BigInt(g.rows)); }
    return {lattice: [x[0], x[1], y[0], y[1]], phase: s.frac, element: [ex[0], ex[1], ey[0], ey[1]],
            texel: [mod(mod(wu, pw) * (e.density[0] % pw), pw), mod(mod(wv, ph) * (e.density[1] % ph), ph)],
            fraction: [fu, fv], field: e.field ? fieldOrigin(lat, e.field, [wu, wv]) : [0, 0]};
  };

  // dynbtf.export.web.shader.field_origin: where the repeat starts on the entry's label field, in its texels
  function fieldOrigin(lat, f, whole) {
    var dims = [f.width, f.height];
    return whole.map(function (w, k) {
      if (f.wrap === 'repeat') return (w - Math.floor(w / f.size) * f.size) / f.size * dims[k];
      var bound = (lat.local_repeats + 1) / f.size * dims[k] + dims[k] + 1;
      return Math.min(Math.max(w / f.size * dims[k], -bound), bound);
    });
  }

  // ------------------------------------------------------------------ GL resources
  var FORMATS = {
    RGBA32F: ['RGBA32F', 'RGBA', 'FLOAT', Float32Array], RGBA16F: ['RGBA16F', 'RGBA', 'HALF_FLOAT', Uint16Array],
    RGBA8: ['RGBA8', 'RGBA', 'UNSIGNED_BYTE', Uint8Array], R32F: ['R32F', 'RED', 'FLOAT', Float32Array],
    R16F: ['R16F', 'RED', 'HALF_FLOAT', Uint16Array], R8: ['R8', 'RED', 'UNSIGNED_BYTE', Uint8Array],
    R16I: ['R16I', 'RED_INTEGER', 'SHORT', Int16Array]
  };
  // texture units of the export's samplers (5..9 are left to the caller, e.g. dynbtf's query pages; 11, 12 the layered programs')
  var UNITS = {plane: 0, lut: 1, lum: 2, fh: 3, fd: 4, cells: 10, guide: 15};

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
      if (e.guidance) r.guide = texture(gl, e.guidance, data.files[e.guidance.file]);
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
    bind(UNITS.guide, gl.TEXTURE_2D, r.guide || this.dummyInt, 'dynbtf_guide');
    gl.uniform1i(u('dynbtf_mode'), e.mode);
    gl.uniform2i(u('dynbtf_plane_size'), e.plane.width, e.plane.height);
    gl.uniform2i(u('dynbtf_density'), e.density[0], e.density[1]);
    gl.uniform1ui(u('dynbtf_seed_state'), e.seed_state);
    gl.uniform1f(u('dynbtf_gamma'), e.gamma || 1.0);
    gl.uniform1i(u('dynbtf_rotation'), e.rotation ? 1 : 0);
    gl.uniform1f(u('dynbtf_frame_exponent'), e.frame_exponent || 1.0);
    gl.uniform1f(u('dynbtf_scale_log'), e.scale_log || 0.0);
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
    var el = e.elements;  // struct's per-element variation: the element grid, its strengths and hash state, the joints
    gl.uniform4i(u('dynbtf_element_grid'), el ? el.grid[0] : 1, el ? el.grid[1] : 1, el ? el.grid[2] : 0, el ? el.grid[3] : 1);
    gl.uniform2f(u('dynbtf_element_phase'), el ? el.grid[4] : 0.0, el ? el.grid[5] : 0.0);
    gl.uniform2f(u('dynbtf_variation'), el ? el.brightness : 0.0, el ? el.tint : 0.0);
    gl.uniform1ui(u('dynbtf_variation_state'), el ? el.state : 0);
    gl.uniform1i(u('dynbtf_joint_start'), el ? t.joints.start : 0);
    var f = e.field;  // a label field laid over the plane (guided synthesis's target)
    gl.uniform2i(u('dynbtf_field_size'), f ? f.width : 1, f ? f.height : 1);
    gl.uniform2f(u('dynbtf_field_scale'), f ? f.width / f.size : 0.0, f ? f.height / f.size : 0.0);
    gl.uniform1i(u('dynbtf_field_wrap'), f && f.wrap === 'repeat' ? 1 : 0);
    var g = e.guidance, states = new Uint32Array(64);  // guided: labels and target, the candidates' hash states
    if (e.states) states.set(e.states.slice(0, 64));
    gl.uniform1i(u('dynbtf_guide_row'), g ? g.row : 1);
    gl.uniform1i(u('dynbtf_guide_target_start'), g ? g.target.start : 0);
    gl.uniform1i(u('dynbtf_guide_candidates'), g ? e.candidates : 1);
    gl.uniform4uiv(u('dynbtf_guide_states'), states);
    gl.uniform1f(u('dynbtf_guide_softness'), g ? e.softness : 1.0);
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

  // ------------------------------------------------------------------ layered exports (dynbtf.export.web.layered)
  var pendingLayered = null;
  DynBTF.layered = function (manifest, shader) { pendingLayered = {manifest: manifest, shader: shader}; };

  // Load layered.js, its own files (the mask) and each layer's export from `base`:
  // {manifest, shader, files: {name: ArrayBuffer}, layers: [what DynBTF.load gives, per layer]}.
  DynBTF.loadLayered = function (base) {
    base = base || '';
    pendingLayered = null;
    return loadScript(base + 'layered.js').then(function () {
      var L = pendingLayered && pendingLayered.manifest;
      if (!L || L.format !== 'dynbtf-web-layered') throw new Error('layered.js: unreadable (it defines no dynbtf layered export)');
      if (L.version !== 1) throw new Error('layered.js: layered export version ' + L.version + ' is not supported (expected 1)');
      var names = Object.keys(L.files);
      return Promise.all(names.map(function (n) { return loadScript(base + n + '.js'); })).then(function () {
        var files = {};
        names.forEach(function (n) {
          var entry = pending.files[n];
          if (!entry) throw new Error(n + '.js: missing or unreadable (it defines no data for ' + n + ')');
          files[n] = decodeBase64(n + '.js', entry, L.files[n].bytes);
        });
        var layers = [], chain = Promise.resolve();
        L.layers.forEach(function (layer) {  // one after the other: each layer's scripts fill the same slots
          chain = chain.then(function () { return DynBTF.load(base + layer.directory); })
            .then(function (data) { layers.push(data); });
        });
        return chain.then(function () {
          return {manifest: L, shader: pendingLayered.shader, files: files, layers: layers};
        });
      });
    });
  };

  function fmod(a, n) { var r = a % n; return r < 0 ? r + n : r; }  // NumPy's float mod (n > 0)

  // dynbtf.export.web.layered.mask_origin: the float64 part of a surface position (u, v) for the shader's mask.
  DynBTF.maskOrigin = function (mask, u, v) {
    if (mask.kind === 'noise') {
      var pu = u / mask.scale, pv = v / mask.scale, cu = Math.floor(pu), cv = Math.floor(pv);
      var x = words(BigInt(cu)), y = words(BigInt(cv));
      return {cell: [x[0], x[1], y[0], y[1]], offset: [pu - cu, pv - cv]};
    }
    var repeat = mask.wrap === 'repeat';
    return {cell: [0, 0, 0, 0], offset: repeat ? [fmod(u, mask.size), fmod(v, mask.size)] : [u, v]};
  };

  // dynbtf.synthesis.hash in 32-bit integer arithmetic (for a noise mask rasterized into an image)
  function mix32(x) {
    x = (x ^ (x >>> 16)) >>> 0; x = Math.imul(x, 0x7FEB352D) >>> 0;
    x = (x ^ (x >>> 15)) >>> 0; x = Math.imul(x, 0x846CA68B) >>> 0;
    return (x ^ (x >>> 16)) >>> 0;
  }
  function fold(h, k) { var w = words(BigInt(k)); return mix32((mix32((h ^ w[0]) >>> 0) ^ w[1]) >>> 0); }

  // The value of a noise mask (dynbtf.layered.NoiseMask) at (u, v).
  DynBTF.noiseMask = function (mask, u, v) {
    var pu = u / mask.scale, pv = v / mask.scale, iu = Math.floor(pu), iv = Math.floor(pv);
    function corner(dx, dy) { return fold(fold(mask.seed_state, iu + dx), iv + dy) / 4294967295; }
    var fu = pu - iu, fv = pv - iv, su = fu * fu * (3 - 2 * fu), sv = fv * fv * (3 - 2 * fv);
    var n = (corner(0, 0) * (1 - su) + corner(1, 0) * su) * (1 - sv) + (corner(0, 1) * (1 - su) + corner(1, 1) * su) * sv;
    return Math.min(1, Math.max(0, 0.5 + mask.contrast * (n - 0.5)));
  };

  // texture units of the layered programs (the layers' own are UNITS; 5..9 are the caller's)
  var LAYER_UNITS = {mask: 11, previous: 12};

  // A layered renderer: one Renderer per layer, the mask as a texture (an image mask can be painted).
  DynBTF.LayeredRenderer = function (gl, data) {
    var L = data.manifest;
    this.gl = gl;
    this.manifest = L;
    this.glsl = data.shader;
    this.layers = data.layers.map(function (d) { return new DynBTF.Renderer(gl, d); });
    this.width = L.width;
    this.mask = {kind: L.mask.kind, size: L.mask.size, wrap: L.mask.wrap, scale: L.mask.scale,
                 contrast: L.mask.contrast, seed_state: L.mask.seed_state};
    this.maskTexture = gl.createTexture();
    if (L.mask.kind === 'image') {
      var t = L.mask.texture;
      this.setMaskImage(new Float32Array(data.files[t.file].slice(0)), t.width, t.height, L.mask.size, L.mask.wrap);
    } else {
      this.uploadMask(new Float32Array(1), 1, 1);  // a stand-in: the noise needs no texture
    }
  };

  DynBTF.LayeredRenderer.prototype.uploadMask = function (values, width, height) {
    var gl = this.gl;
    gl.activeTexture(gl.TEXTURE0 + LAYER_UNITS.mask);
    gl.bindTexture(gl.TEXTURE_2D, this.maskTexture);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, width, height, 0, gl.RED, gl.FLOAT, values);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  };

  // Make the mask an image (values in [0, 1], row 0 at v = 0) over `size` uv units, repeated or clamped.
  DynBTF.LayeredRenderer.prototype.setMaskImage = function (values, width, height, size, wrap) {
    if (!(size > 0)) throw new Error('mask size: expected a positive number of uv units, got ' + size);
    this.mask = {kind: 'image', size: size, wrap: wrap, values: values, width: width, height: height};
    this.uploadMask(values, width, height);
  };

  // Set every mask texel whose centre lies within `radius` uv units of the surface point (u, v) to `value`.
  DynBTF.LayeredRenderer.prototype.paint = function (u, v, radius, value) {
    var k = this.mask;
    if (k.kind !== 'image') throw new Error('paint: the mask is value noise; make it an image first');
    var w = k.width, h = k.height, s = k.size, repeat = k.wrap === 'repeat';
    var cx = (repeat ? fmod(u, s) : u) / s * w - 0.5, cy = (repeat ? fmod(v, s) : v) / s * h - 0.5;
    var rx = radius / s * w, ry = radius / s * h, changed = 0;
    for (var j = Math.floor(cy - ry); j <= Math.ceil(cy + ry); ++j) {
      for (var i = Math.floor(cx - rx); i <= Math.ceil(cx + rx); ++i) {
        var du = (i - cx) / w * s, dv = (j - cy) / h * s;
        if (du * du + dv * dv > radius * radius) continue;
        var ii = repeat ? fmod(i, w) : i, jj = repeat ? fmod(j, h) : j;
        if (ii < 0 || jj < 0 || ii >= w || jj >= h) continue;
        if (k.values[jj * w + ii] !== value) { k.values[jj * w + ii] = value; changed += 1; }
      }
    }
    if (changed) this.uploadMask(k.values, w, h);
    return changed;
  };

  // The current mask as an image over `size` uv units (a noise mask sampled at the texel centres).
  DynBTF.LayeredRenderer.prototype.maskImage = function (texels, size) {
    var k = this.mask;
    if (k.kind === 'image') return k;
    var values = new Float32Array(texels * texels);
    for (var j = 0; j < texels; ++j) {
      for (var i = 0; i < texels; ++i) values[j * texels + i] = DynBTF.noiseMask(k, (i + 0.5) / texels * size, (j + 0.5) / texels * size);
    }
    return {kind: 'image', size: size, wrap: 'repeat', values: values, width: texels, height: texels};
  };

  // Compile layer k's program: its dynbtf.glsl, layered.glsl, then `main`.
  DynBTF.LayeredRenderer.prototype.program = function (k, main, vertex) {
    return this.layers[k].program(this.glsl + '\n' + main, vertex);
  };

  // Make `program` (layer k's) current with the layer's method, the mask and the boundary's uniforms.
  DynBTF.LayeredRenderer.prototype.use = function (program, k) {
    var gl = this.gl, layer = this.manifest.layers[k], mask = this.mask;
    this.layers[k].use(program, layer.method);
    function u(n) { return gl.getUniformLocation(program, n); }
    gl.activeTexture(gl.TEXTURE0 + LAYER_UNITS.mask);
    gl.bindTexture(gl.TEXTURE_2D, this.maskTexture);
    gl.uniform1i(u('dynbtf_mask'), LAYER_UNITS.mask);
    gl.uniform1i(u('dynbtf_mask_kind'), mask.kind === 'noise' ? 1 : 0);
    gl.uniform1f(u('dynbtf_mask_size'), mask.size || 1.0);
    gl.uniform1i(u('dynbtf_mask_repeat'), mask.wrap === 'repeat' ? 1 : 0);
    gl.uniform1f(u('dynbtf_mask_scale'), mask.scale || 1.0);
    gl.uniform1f(u('dynbtf_mask_contrast'), mask.contrast || 1.0);
    gl.uniform1ui(u('dynbtf_mask_seed_state'), mask.seed_state || 0);
    gl.uniform1i(u('dynbtf_layer_index'), k);
    gl.uniform1f(u('dynbtf_layer_width'), this.width);
    gl.uniform4fv(u('dynbtf_layer_height_map'), layer.height.map);
    gl.uniform1f(u('dynbtf_layer_height_offset'), layer.height.offset);
    gl.uniform2f(u('dynbtf_layer_height_range'), layer.height.low, layer.height.high);
    gl.uniform4fv(u('dynbtf_layer_height_table'), layer.height.table);
    gl.uniform1i(u('u_previous'), LAYER_UNITS.previous);
    if (k === 0) this.bindPrevious(null);  // layer 0 renders into the texture layer 1 reads: no feedback loop
  };

  // Bind layer 0's result (a texture) where layer 1's program reads it.
  DynBTF.LayeredRenderer.prototype.bindPrevious = function (texture) {
    var gl = this.gl;
    gl.activeTexture(gl.TEXTURE0 + LAYER_UNITS.previous);
    gl.bindTexture(gl.TEXTURE_2D, texture);
  };

  // ------------------------------------------------------------------ the viewer page
  // attribute locations are fixed: one vertex array serves every program (a layered material has two)
  var VERTEX = [
    '#version 300 es',
    'layout(location = 0) in vec3 a_position; layout(location = 1) in vec3 a_normal;',
    'layout(location = 2) in vec3 a_tangent; layout(location = 3) in vec2 a_uv;',
    'uniform mat4 u_view_projection; uniform vec2 u_local_origin; uniform float u_scale; uniform float u_span;',
    'out vec3 v_position; out vec3 v_normal; out vec3 v_tangent; out vec2 v_local; out vec2 v_mask;',
    'void main() {',
    '  v_position = a_position; v_normal = a_normal; v_tangent = a_tangent;',
    '  v_local = u_local_origin + a_uv * u_scale;',  // exemplar repeats from the origin (float32)
    '  v_mask = a_uv * u_span;',                     // a layered material's mask: uv units from the origin
    '  gl_Position = u_view_projection * vec4(a_position, 1.0);',
    '}'].join('\n');
  var FRAME = [  // the local frame at a fragment: w_view and w_light in it (shared by both fragment programs)
    'in vec3 v_position; in vec3 v_normal; in vec3 v_tangent; in vec2 v_local; in vec2 v_mask;',
    'uniform uvec4 u_lattice; uniform float u_phase; uniform ivec2 u_texel; uniform vec2 u_field; uniform uvec4 u_element;',
    'uniform vec3 u_camera; uniform vec3 u_light; uniform float u_intensity;',
    'out vec4 color;',
    'vec3 srgb(vec3 c) { c = clamp(c, 0.0, 1.0);',
    '  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c)); }',
    'void local_frame(out vec3 wv_local, out vec3 wl_local) {',
    '  vec3 n = normalize(v_normal);',
    '  vec3 t = normalize(v_tangent - dot(v_tangent, n) * n);',
    '  vec3 b = cross(n, t);',  // (t, b, n) right-handed: x along +u, y along +v, z = normal
    '  vec3 wv = normalize(u_camera - v_position);',
    '  wv_local = vec3(dot(wv, t), dot(wv, b), dot(wv, n));',
    '  wl_local = vec3(dot(u_light, t), dot(u_light, b), dot(u_light, n));',
    '}',
    'DynbtfOrigin origin() { DynbtfOrigin o; o.lattice = u_lattice; o.phase = u_phase; o.texel = u_texel;',
    '  o.field = u_field; o.element = u_element; return o; }',
    ''].join('\n');
  var SHADE = FRAME + [
    'void main() {',
    '  vec3 wv_local, wl_local;',
    '  local_frame(wv_local, wl_local);',
    '  vec3 value = dynbtf_eval(origin(), v_local, wv_local, wl_local);',  // pi f_r, excluding the cosine
    '  color = vec4(srgb(value * max(wl_local.z, 0.0) * u_intensity), 1.0);',
    '}'].join('\n');
  // a layered material's pass: layer 0 writes (value, height) to a float target, layer 1 mixes and shades
  var LAYER_PASS = FRAME + [
    'uniform uvec4 u_mask_cell; uniform vec2 u_mask_offset; uniform highp sampler2D u_previous;',
    'void main() {',
    '  vec3 wv_local, wl_local;',
    '  local_frame(wv_local, wl_local);',
    '  DynbtfMaskOrigin mo; mo.cell = u_mask_cell; mo.offset = u_mask_offset;',
    '  vec4 previous = dynbtf_layer_index == 1 ? texelFetch(u_previous, ivec2(gl_FragCoord.xy), 0) : vec4(0.0);',
    '  vec4 r = dynbtf_layer_pass(origin(), v_local, mo, v_mask, wv_local, wl_local, previous);',
    '  color = dynbtf_layer_index == 0 ? r : vec4(srgb(r.rgb * max(wl_local.z, 0.0) * u_intensity), 1.0);',
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

  function mesh(gl, geometry) {  // attributes at VERTEX's locations
    var vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    [[geometry.position, 3], [geometry.normal, 3], [geometry.tangent, 3], [geometry.uv, 2]].forEach(function (a, loc) {
      var b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(a[0]), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, a[1], gl.FLOAT, false, 0, 0);
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

  // The camera of the page's controls: eye position, up vector and view-projection matrix (column-major).
  function camera(view, aspect) {
    var eye = direction(view.viewTheta, view.viewPhi).map(function (v) { return v * view.distance; });
    var up = view.viewTheta < 1e-3 ? [0, 1, 0] : [0, 0, 1];
    return {eye: eye, up: up, aspect: aspect,
            viewProjection: multiply(perspective(0.7, aspect, 0.05, 50), lookAt(eye, up))};
  }

  // The mesh point under the canvas position (x, y) in [-1, 1]^2 (y up): its uv in [0, 1]^2, or null.
  DynBTF.pick = function (shape, cam, x, y) {
    var f = cam.eye.map(function (v) { return -v; }), lf = Math.hypot(f[0], f[1], f[2]);
    f = f.map(function (v) { return v / lf; });
    var up = cam.up, side = [f[1] * up[2] - f[2] * up[1], f[2] * up[0] - f[0] * up[2], f[0] * up[1] - f[1] * up[0]];
    var ls = Math.hypot(side[0], side[1], side[2]) || 1;
    side = side.map(function (v) { return v / ls; });
    var top = [side[1] * f[2] - side[2] * f[1], side[2] * f[0] - side[0] * f[2], side[0] * f[1] - side[1] * f[0]];
    var ty = Math.tan(0.35), tx = ty * cam.aspect, e = cam.eye;
    var d = [0, 1, 2].map(function (i) { return f[i] + side[i] * x * tx + top[i] * y * ty; });
    if (shape === 'plane') {
      if (Math.abs(d[2]) < 1e-12) return null;
      var t = -e[2] / d[2];
      if (!(t > 0)) return null;
      var px = e[0] + t * d[0], py = e[1] + t * d[1];
      if (Math.abs(px) > 1 || Math.abs(py) > 1) return null;
      return [(px + 1) / 2, (py + 1) / 2];
    }
    var a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2], b = 2 * (e[0] * d[0] + e[1] * d[1] + e[2] * d[2]);
    var c = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] - 1, disc = b * b - 4 * a * c;
    if (disc < 0) return null;
    var s = (-b - Math.sqrt(disc)) / (2 * a);
    if (!(s > 0)) return null;
    var p = [e[0] + s * d[0], e[1] + s * d[1], e[2] + s * d[2]];
    var u = Math.atan2(p[1], p[0]) / (2 * Math.PI);
    return [u - Math.floor(u), 1 - Math.acos(Math.max(-1, Math.min(1, p[2]))) / Math.PI];
  };

  function setCamera(gl, program, cam, view) {
    function u(n) { return gl.getUniformLocation(program, n); }
    gl.uniformMatrix4fv(u('u_view_projection'), false, cam.viewProjection);
    gl.uniform3fv(u('u_camera'), cam.eye);
    gl.uniform3fv(u('u_light'), direction(view.lightTheta, view.lightPhi));
    gl.uniform1f(u('u_intensity'), view.intensity);
  }

  function setOrigin(gl, program, o, scale) {
    function u(n) { return gl.getUniformLocation(program, n); }
    gl.uniform2f(u('u_local_origin'), o.fraction[0], o.fraction[1]);
    gl.uniform1f(u('u_scale'), scale);
    gl.uniform4ui(u('u_lattice'), o.lattice[0], o.lattice[1], o.lattice[2], o.lattice[3]);
    gl.uniform1f(u('u_phase'), o.phase);
    gl.uniform2i(u('u_texel'), o.texel[0], o.texel[1]);
    gl.uniform2f(u('u_field'), o.field[0], o.field[1]);
    gl.uniform4ui(u('u_element'), o.element[0], o.element[1], o.element[2], o.element[3]);
  }

  function drawMesh(gl, shape) {
    gl.bindVertexArray(shape.vao);
    gl.drawElements(gl.TRIANGLES, shape.count, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(null);
  }

  function glName(gl) {
    var debug = gl.getExtension('WEBGL_debug_renderer_info');
    return debug ? gl.getParameter(debug.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
  }

  // One material: its methods in the menu, the slider in exemplar repeats per uv unit.
  function singleScene(gl, data, ui) {
    var renderer = new DynBTF.Renderer(gl, data), m = data.manifest;
    var program = renderer.program(SHADE, VERTEX);
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
    return {
      methodName: function (v) { return DynBTF.methodName(m, v); },
      info: m.kind + ' model' + (m.source ? ' ' + m.source : '') + ', ' + m.precision + ' textures, ' +
        Object.keys(m.methods).length + ' method(s)' + (m.auto ? ' (' + m.auto.line + ')' : '') + '; ' +
        m.channels + ' positional channels, decoder ' + m.layers + ' x ' + m.hidden,
      draw: function (view, cam, shape) {
        var o = DynBTF.origin(m, view.method, view.origin * view.scale, view.origin * view.scale);
        renderer.use(program, view.method);
        gl.bindFramebuffer(gl.FRAMEBUFFER, null);
        gl.clearColor(0.08, 0.08, 0.09, 1);
        gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
        setCamera(gl, program, cam, view);
        setOrigin(gl, program, o, view.scale);
        drawMesh(gl, shape);
      }
    };
  }

  // A float render target (colour texture and depth) for layer 0's pass.
  function floatTarget(gl, width, height, old) {
    if (old && old.width === width && old.height === height) return old;
    var half = !gl.getExtension('EXT_color_buffer_float');
    if (half && !gl.getExtension('EXT_color_buffer_half_float')) {
      throw new Error('This browser cannot render into float textures (EXT_color_buffer_float): the layered viewer needs it.');
    }
    var colour = old ? old.colour : gl.createTexture(), depth = old ? old.depth : gl.createRenderbuffer();
    var fb = old ? old.fb : gl.createFramebuffer();
    gl.bindTexture(gl.TEXTURE_2D, colour);
    gl.texImage2D(gl.TEXTURE_2D, 0, half ? gl.RGBA16F : gl.RGBA32F, width, height, 0, gl.RGBA, half ? gl.HALF_FLOAT : gl.FLOAT, null);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, width, height);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, colour, 0);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) {
      throw new Error('the float render target of the layered viewer is incomplete on this GPU');
    }
    return {fb: fb, colour: colour, depth: depth, width: width, height: height};
  }

  // Two materials and their mask: the slider in uv units across the mesh; the mask can be painted and loaded.
  function layeredScene(gl, data, ui) {
    var L = data.manifest, renderer = new DynBTF.LayeredRenderer(gl, data);
    var programs = [renderer.program(0, LAYER_PASS, VERTEX), renderer.program(1, LAYER_PASS, VERTEX)];
    var target = null;
    document.getElementById('layered').hidden = false;
    document.getElementById('method-label').hidden = true;
    document.getElementById('scale-label').textContent = 'uv units across the mesh';
    ui.scale.min = 0.05;
    ui.scale.step = 'any';
    var most = Math.min.apply(null, L.layers.map(function (layer) { return 4096 / layer.scale; }));
    ui.scale.max = Math.min(64, most);
    ui.scale.value = L.span;
    ui.width.value = L.width;
    ui.width.max = Math.max(0.5, 2 * L.width);
    function describeMask() {
      var k = renderer.mask;
      return k.kind === 'noise' ? 'value noise (' + k.scale + ' uv units per cell, contrast ' + k.contrast + ')' :
        'an image of ' + k.width + 'x' + k.height + ' texels over ' + k.size + ' uv units (' + k.wrap + ')';
    }
    var scene = {
      renderer: renderer,
      methodName: function (v) { return v; },
      info: 'layered material: ' + L.layers.map(function (layer, k) {
        return 'layer ' + k + ' ' + layer.kind + ' ' + layer.method + ' at ' + layer.scale + ' repeats per uv unit';
      }).join(', ') + '; ' + L.precision + ' textures',
      describeMask: describeMask,
      // the mask as an image (a noise mask rasterized over the uv units the mesh shows), for painting
      editableMask: function (span) {
        var k = renderer.mask;
        if (k.kind !== 'image') {
          var image = renderer.maskImage(256, span);
          renderer.setMaskImage(image.values, image.width, image.height, image.size, image.wrap);
        }
        return renderer.mask;
      },
      draw: function (view, cam, shape) {
        var canvas = gl.canvas;
        target = floatTarget(gl, canvas.width, canvas.height, target);
        renderer.width = view.width;
        var mo = DynBTF.maskOrigin(renderer.mask, view.origin, view.origin);
        for (var k = 0; k < 2; ++k) {
          var layer = L.layers[k], program = programs[k], m = data.layers[k].manifest;
          var scale = view.scale * layer.scale;
          var o = DynBTF.origin(m, layer.method, view.origin * layer.scale, view.origin * layer.scale);
          gl.bindFramebuffer(gl.FRAMEBUFFER, k === 0 ? target.fb : null);
          if (k === 0) gl.clearColor(0, 0, 0, 0); else gl.clearColor(0.08, 0.08, 0.09, 1);
          gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
          renderer.use(program, k);
          if (k === 1) renderer.bindPrevious(target.colour);
          setCamera(gl, program, cam, view);
          setOrigin(gl, program, o, scale);
          gl.uniform1f(gl.getUniformLocation(program, 'u_span'), view.scale);
          gl.uniform4ui(gl.getUniformLocation(program, 'u_mask_cell'), mo.cell[0], mo.cell[1], mo.cell[2], mo.cell[3]);
          gl.uniform2f(gl.getUniformLocation(program, 'u_mask_offset'), mo.offset[0], mo.offset[1]);
          drawMesh(gl, shape);
        }
      }
    };
    return scene;
  }

  // A grey PNG of a mask image (its values as 8-bit levels: what `dynbtf synth --mask` reads back), as a data URL.
  var maskPng = DynBTF.maskPng = function (mask) {
    var c = document.createElement('canvas');
    c.width = mask.width; c.height = mask.height;
    var ctx = c.getContext('2d'), pixels = ctx.createImageData(mask.width, mask.height);
    for (var i = 0; i < mask.width * mask.height; ++i) {
      var level = Math.round(Math.min(1, Math.max(0, mask.values[i])) * 255);
      pixels.data[4 * i] = pixels.data[4 * i + 1] = pixels.data[4 * i + 2] = level;
      pixels.data[4 * i + 3] = 255;
    }
    ctx.putImageData(pixels, 0, 0);
    return c.toDataURL('image/png');
  };

  // The mask values of a loaded <img> (the mean of its channels' levels over 255, as `dynbtf synth --mask` reads
  // it): {values, width, height}.
  var imageMaskValues = DynBTF.imageMaskValues = function (image) {
    var c = document.createElement('canvas');
    c.width = image.naturalWidth; c.height = image.naturalHeight;
    var ctx = c.getContext('2d');
    ctx.drawImage(image, 0, 0);
    var data = ctx.getImageData(0, 0, c.width, c.height).data, values = new Float32Array(c.width * c.height);
    for (var i = 0; i < values.length; ++i) values[i] = (data[4 * i] + data[4 * i + 1] + data[4 * i + 2]) / (3 * 255);
    return {values: values, width: c.width, height: c.height};
  };

  function startViewer(canvas, layered) {
    var gl = canvas.getContext('webgl2', {antialias: false});
    if (!gl) { showError('This browser has no WebGL2: the viewer needs it.'); return; }
    (layered ? DynBTF.loadLayered('') : DynBTF.load('')).then(function (data) {
      var ui = {};
      ['shape', 'method', 'scale', 'origin', 'view-theta', 'view-phi', 'distance', 'light-theta', 'light-phi',
       'intensity', 'resolution'].concat(layered ? ['width', 'paint', 'paint-layer', 'brush'] : []).forEach(function (id) {
        ui[id] = document.getElementById(id);
      });
      var scene = layered ? layeredScene(gl, data, ui) : singleScene(gl, data, ui);
      var meshes = {plane: mesh(gl, plane()), sphere: mesh(gl, sphere(96, 192))};
      // initial settings from the address: index.html?shape=sphere&method=hex&origin=1e6&light-theta=60 ...
      new URLSearchParams(window.location.search).forEach(function (v, k) {
        if (!ui[k]) throw new Error('unknown page parameter ' + k + ' (expected one of ' + Object.keys(ui).join(', ') + ')');
        if (ui[k].type === 'checkbox') { ui[k].checked = v === '1' || v === 'true'; return; }
        if (k === 'method') v = scene.methodName(v);  // method=auto: the model's choice
        ui[k].value = v;
        if (ui[k].value !== v && ui[k].tagName === 'SELECT') throw new Error('page parameter ' + k + '=' + v + ' is not one of its choices');
      });
      var name = glName(gl), software = /SwiftShader|llvmpipe|Software/.test(name);
      if (software && !new URLSearchParams(window.location.search).has('resolution')) {
        ui.resolution.value = '0.25';  // software GL: a few frames per second at most
      }
      var info = document.getElementById('info');
      function showInfo() {
        info.textContent = scene.info + (layered ? '; mask: ' + scene.describeMask() : '') + '. GL: ' + name +
          (software ? ' (software GL: a few frames per second at most)' : '');
      }
      showInfo();
      function value(id) {
        var v = parseFloat(ui[id].value);
        var out = document.getElementById(id + '-value');
        if (out) out.textContent = ui[id].value;
        return v;
      }
      function currentView() {
        var origin = Number(ui.origin.value.trim() || '0');
        if (!isFinite(origin)) throw new Error('uv origin: expected a number such as 0 or 1e6, got ' + ui.origin.value);
        return {method: ui.method.value, scale: value('scale'), origin: origin, viewTheta: value('view-theta'),
                viewPhi: value('view-phi'), distance: value('distance'), lightTheta: value('light-theta'),
                lightPhi: value('light-phi'), intensity: value('intensity'), width: layered ? value('width') : 0};
      }
      function currentCamera(view) { return camera(view, canvas.width / Math.max(canvas.height, 1)); }
      // layered: paint the mask where the pointer is (in paint mode)
      function paintAt(e) {
        var view = currentView(), rect = canvas.getBoundingClientRect();
        var x = 2 * (e.clientX - rect.left) / rect.width - 1, y = 1 - 2 * (e.clientY - rect.top) / rect.height;
        var uv = DynBTF.pick(ui.shape.value, currentCamera(view), x, y);
        if (!uv) return;
        var before = scene.renderer.mask.kind;
        scene.editableMask(view.scale);
        scene.renderer.paint(view.origin + uv[0] * view.scale, view.origin + uv[1] * view.scale, value('brush'),
                             parseFloat(ui['paint-layer'].value));
        if (before !== scene.renderer.mask.kind) showInfo();
      }
      // orbit: drag to turn the camera (or paint, in paint mode), wheel to move it closer
      var drag = null, painting = false;
      canvas.addEventListener('mousedown', function (e) {
        if (layered && ui.paint.checked) { painting = true; paintAt(e); return; }
        drag = [e.clientX, e.clientY];
      });
      window.addEventListener('mouseup', function () { drag = null; painting = false; });
      window.addEventListener('mousemove', function (e) {
        if (painting) { paintAt(e); return; }
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
      if (layered) {
        document.getElementById('mask-new').addEventListener('click', function () {
          var span = value('scale'), n = 256;
          scene.renderer.setMaskImage(new Float32Array(n * n), n, n, span, 'repeat');
          showInfo();
        });
        document.getElementById('mask-save').addEventListener('click', function () {
          this.href = maskPng(scene.editableMask(value('scale')));
          showInfo();
        });
        document.getElementById('mask-file').addEventListener('change', function () {
          var file = this.files && this.files[0];
          if (!file) return;
          var reader = new FileReader();
          reader.onload = function () {
            var image = new Image();
            image.onload = function () {
              var read = imageMaskValues(image), k = scene.renderer.mask;
              scene.renderer.setMaskImage(read.values, read.width, read.height, k.kind === 'image' ? k.size : value('scale'),
                                          k.kind === 'image' ? k.wrap : 'repeat');
              showInfo();
            };
            image.onerror = function () { showError(file.name + ': not an image this browser can read'); };
            image.src = reader.result;
          };
          reader.readAsDataURL(file);
        });
      }
      DynBTF.viewer = {scene: scene, ui: ui, canvas: canvas, camera: function () { return currentCamera(currentView()); }};
      var frames = -1, last = 0, drawn = 0, frameError = false, fps = document.getElementById('fps');  // counted from the first frame's start
      function frame(now) {
        try {
          var view = currentView();
          var factor = parseFloat(ui.resolution.value) || 1;
          var w = Math.max(1, Math.round(canvas.clientWidth * factor)), h = Math.max(1, Math.round(canvas.clientHeight * factor));
          if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
          gl.viewport(0, 0, canvas.width, canvas.height);
          gl.enable(gl.DEPTH_TEST);
          scene.draw(view, currentCamera(view), meshes[ui.shape.value]);
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
    var layeredPage = document.currentScript.getAttribute('data-viewer') === 'layered';
    window.addEventListener('load', function () { startViewer(document.getElementById('view'), layeredPage); });
  }
})();
