"""Run a web export's shader in headless Chromium: evaluate queries, time frames, check the viewer.

The shader of :mod:`dynbtf.export.web.exporter` is only as good as what a browser computes with it.
:func:`eval_in_browser` evaluates ``(uv, w_view, w_light)`` queries with the exported shader in
Chromium's WebGL2 (rendered into a float32 target, ``EXT_color_buffer_float``, and read back),
through the export's own ``viewer.js`` (its loader and its float64 repeat-origin split), so the
result can be compared with :meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` on the same queries.

Chromium runs with ``--headless``; ``gl="swiftshader"`` (default) forces its software GL
(SwiftShader, on any machine), ``gl="gpu"`` lets it use the machine's GPU when it has one.
Pages are written next to the export (so its relative ``<script>`` links resolve), loaded with
``--dump-dom`` and deleted; console messages are collected from Chromium's log.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dynbtf.errors import InputError

__all__ = ["find_chromium", "CHROMIUM_FLAGS", "PageRun", "run_page", "eval_in_browser", "lattice_in_browser",
           "BrowserResult", "eval_layered_in_browser", "LayeredBrowserResult", "time_frames", "time_layered_frames",
           "FrameTimes"]

#: Flags for a quiet, offline, sandbox-free headless run (each run also gets a fresh profile dir).
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars", "--allow-file-access-from-files")
# (no --disable-gpu: with it Chromium composites in software and reads every WebGL frame back, which it
# reports on the page's console as "GPU stall due to ReadPixels")
_GL_FLAGS = {"swiftshader": ("--use-angle=swiftshader", "--enable-unsafe-swiftshader"),
             "gpu": ("--enable-gpu", "--ignore-gpu-blocklist", "--enable-unsafe-swiftshader")}


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome executable (``$DYNBTF_CHROMIUM`` first), or ``None``."""
    env = os.environ.get("DYNBTF_CHROMIUM")
    if env and Path(env).exists():
        return env
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


@dataclass
class PageRun:
    """What a page left in its DOM and console.

    ``dom`` is the serialized DOM after the run, ``console`` the page's console messages
    (Chromium's log lines), ``screenshot`` the PNG path if one was taken.
    """

    dom: str
    console: list[str] = field(default_factory=list)
    screenshot: Path | None = None

    def element(self, element_id: str) -> str | None:
        """Text of the ``<pre id=element_id>`` element, unescaped, or None."""
        import html

        m = re.search(rf'<pre id="{re.escape(element_id)}"[^>]*>(.*?)</pre>', self.dom, re.S)
        return None if m is None else html.unescape(m.group(1))


def run_page(page, *, screenshot=None, window=(1280, 720), timeout: float = 300.0, gl: str = "swiftshader",
             budget_ms: int | None = 60000, chromium: str | None = None, query: str = "",
             extra_flags: tuple[str, ...] = ()) -> PageRun:
    """Load ``page`` (an HTML file) in headless Chromium; return its DOM and console messages.

    ``budget_ms`` is Chromium's virtual-time budget: how long (in page time) scripts and
    animation frames may run before the DOM is dumped. ``None``: real time, and the DOM is
    dumped when the page has loaded (what timing pages need: virtual time also virtualizes
    ``performance.now()``). ``query`` is appended to the page's address after ``?``; ``extra_flags``
    go to Chromium's command line (e.g. ``--use-angle=vulkan`` to pick a GPU back end).
    """
    exe = chromium or find_chromium()
    if exe is None:
        raise InputError("no Chromium executable found (install Debian's 'chromium' or set DYNBTF_CHROMIUM)")
    if gl not in _GL_FLAGS:
        raise InputError(f"gl: expected one of {sorted(_GL_FLAGS)}, got {gl!r}")
    page = Path(page).resolve()
    url = page.as_uri() + (f"?{query}" if query else "")
    with tempfile.TemporaryDirectory(prefix="dynbtf-chromium-") as profile:
        flags = [exe, *CHROMIUM_FLAGS, *_GL_FLAGS[gl], *extra_flags, f"--user-data-dir={profile}",
                 f"--window-size={window[0]},{window[1]}", "--enable-logging=stderr", "--v=0"]
        if budget_ms is not None:
            flags.append(f"--virtual-time-budget={int(budget_ms)}")
        shot = None
        if screenshot is not None:  # the DOM and the screenshot of one load (a page's shaders compile once)
            shot = Path(screenshot).resolve()
            shot.parent.mkdir(parents=True, exist_ok=True)
            shot.unlink(missing_ok=True)
        done = subprocess.run([*flags, "--dump-dom", *([f"--screenshot={shot}"] if shot else []), url],
                              capture_output=True, text=True, timeout=timeout)
        console = [line for line in done.stderr.splitlines() if ":CONSOLE" in line]
        if shot is not None and not shot.exists():  # a Chromium that takes one of the two per run: load again
            subprocess.run([*flags, f"--screenshot={shot}", url], capture_output=True, text=True,
                           timeout=timeout)
            if not shot.exists():
                raise RuntimeError(f"Chromium wrote no screenshot to {shot}")
    if not done.stdout.strip():
        raise RuntimeError(f"Chromium printed no DOM (exit {done.returncode}): {done.stderr.strip()[-800:]}")
    return PageRun(done.stdout, console, shot)


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")


#: JavaScript the query pages share: base64 in and out, the error box, a float-target context, the queries' origins
#: and directions as texture rows, the result, and ``texture(gl, w, h)``, which returns
#: ``tex(unit, internal, format, type, values)`` (a ``w`` x ``h`` nearest-filtered texture bound to ``unit``).
_PAGE_HELPERS = """  function bytes(b64) { var s = atob(b64), a = new Uint8Array(s.length); for (var i = 0; i < s.length; ++i) a[i] = s.charCodeAt(i); return a.buffer; }
  function b64(buffer) { var a = new Uint8Array(buffer), s = ''; for (var i = 0; i < a.length; i += 8192) s += String.fromCharCode.apply(null, a.subarray(i, i + 8192)); return btoa(s); }
  function fail(e) { var p = document.getElementById('dynbtf-error'); p.textContent = String(e && e.message || e); p.hidden = false; }
  // a WebGL2 context that renders into float32 targets (the query pages read their results back as floats)
  function floatContext() {
    var gl = document.createElement('canvas').getContext('webgl2');
    if (!gl) throw new Error('no WebGL2');
    if (!gl.getExtension('EXT_color_buffer_float')) throw new Error('no EXT_color_buffer_float');
    return gl;
  }
  // per query i, DynBTF.origin of at(i) = [u, v, shift] (exemplar repeats, whole repeats moved into the local uv) as
  // the textures' RGBA rows: lattice words, (texel, the label field's origin as float32 bits), (phase, local u, local v)
  function origins(m, method, n, size, at) {
    var lattice = new Uint32Array(4 * size), texel = new Int32Array(4 * size), local = new Float32Array(4 * size);
    var fieldBits = new Float32Array(texel.buffer), element = new Uint32Array(4 * size);
    for (var i = 0; i < n; ++i) {
      var p = at(i), o = DynBTF.origin(m, method, p[0], p[1]);
      lattice.set(o.lattice, 4 * i);
      element.set(o.element, 4 * i);
      texel[4 * i] = o.texel[0]; texel[4 * i + 1] = o.texel[1];
      fieldBits[4 * i + 2] = o.field[0]; fieldBits[4 * i + 3] = o.field[1];
      local[4 * i] = o.phase; local[4 * i + 1] = o.fraction[0] + p[2]; local[4 * i + 2] = o.fraction[1] + p[2];
    }
    return {lattice: lattice, texel: texel, local: local, element: element};
  }
  // (n, 3) directions as RGBA rows
  function rows(values, n, size) {
    var out = new Float32Array(4 * size);
    for (var i = 0; i < n; ++i) for (var c = 0; c < 3; ++c) out[4 * i + c] = values[3 * i + c];
    return out;
  }
  // the page's result, once WebGL reports no error
  function finish(gl, results) {
    var err = gl.getError();
    if (err !== gl.NO_ERROR) throw new Error('WebGL error ' + err);
    document.getElementById('dynbtf-result').textContent = JSON.stringify(results);
  }
  function texture(gl, w, h) {
    return function (unit, internal, format, type, values) {
      var t = gl.createTexture();
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, t);
      gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, values);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      return t;
    };
  }
  // a w x h float32 RGBA texture, nearest-filtered, bound as its framebuffer's colour: {texture, fb}
  function floatTarget(gl, w, h) {
    var t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, w, h, 0, gl.RGBA, gl.FLOAT, null);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    var fb = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, t, 0);
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) throw new Error('float target incomplete');
    return {texture: t, fb: fb};
  }"""


_QUERY_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>dynbtf queries</title></head><body>
<pre id="dynbtf-result"></pre><pre id="dynbtf-error" hidden></pre>
<script src="viewer.js"></script>
<script>
(function () {
  var job = __JOB__;
__HELPERS__
  DynBTF.load('').then(function (data) {
    var n = job.n, w = job.width, h = Math.ceil(n / w);
    var points = new Float64Array(bytes(job.points)), shift = new Int32Array(bytes(job.shift));
    var view = new Float32Array(bytes(job.view)), light = new Float32Array(bytes(job.light));
    var gl = floatContext();
    var dbg = gl.getExtension('WEBGL_debug_renderer_info');
    var rendererName = dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
    var r = new DynBTF.Renderer(gl, data), m = data.manifest;
    var q = origins(m, job.method, n, w * h, function (i) {
      return [points[2 * i] - shift[i], points[2 * i + 1] - shift[i], shift[i]];
    });
    var vv = rows(view, n, w * h), ll = rows(light, n, w * h);
    var tex = texture(gl, w, h);
    var inputs = 'uniform highp usampler2D q_lattice; uniform highp isampler2D q_texel; uniform highp sampler2D q_local;\\n' +
      'uniform highp sampler2D q_view; uniform highp sampler2D q_light; uniform highp usampler2D q_element;\\n' +
      'DynbtfOrigin q_origin(ivec2 p) { DynbtfOrigin o; o.lattice = texelFetch(q_lattice, p, 0);\\n' +
      '  o.phase = texelFetch(q_local, p, 0).x; ivec4 t = texelFetch(q_texel, p, 0); o.texel = t.xy;\\n' +
      '  o.field = intBitsToFloat(t.zw); o.element = texelFetch(q_element, p, 0); return o; }\\n';
    var programs = {
      rgb: r.program(inputs + 'layout(location = 0) out vec4 result;\\nvoid main() { ivec2 p = ivec2(gl_FragCoord.xy);\\n' +
        '  result = vec4(dynbtf_eval(q_origin(p), texelFetch(q_local, p, 0).yz, texelFetch(q_view, p, 0).xyz,' +
        ' texelFetch(q_light, p, 0).xyz), 1.0); }\\n'),
      lattice: r.program(inputs + 'uniform int q_what;\\nlayout(location = 0) out uvec4 result;\\n' +
        'void main() { ivec2 p = ivec2(gl_FragCoord.xy);\\n' +
        '  DynbtfTriangle t = dynbtf_triangle(q_origin(p), texelFetch(q_local, p, 0).yz);\\n' +
        '  if (q_what < 3) result = uvec4(t.vx[q_what], t.vy[q_what]);\\n' +
        '  else if (q_what == 3) result = uvec4(t.offset[0], t.offset[1]);\\n' +
        '  else result = uvec4(t.offset[2], t.texel); }\\n')
    };
    var results = {renderer: rendererName, debug: []};
    ['rgb', 'lattice'].forEach(function (kind) {
      if (kind === 'lattice' && !job.lattice) return;
      var program = programs[kind];
      r.use(program, job.method);
      var units = [5, 6, 7, 8, 9, 13];
      tex(units[0], gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, q.lattice);
      tex(units[1], gl.RGBA32I, gl.RGBA_INTEGER, gl.INT, q.texel);
      tex(units[2], gl.RGBA32F, gl.RGBA, gl.FLOAT, q.local);
      tex(units[3], gl.RGBA32F, gl.RGBA, gl.FLOAT, vv);
      tex(units[4], gl.RGBA32F, gl.RGBA, gl.FLOAT, ll);
      tex(units[5], gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, q.element);
      ['q_lattice', 'q_texel', 'q_local', 'q_view', 'q_light', 'q_element'].forEach(function (name, j) {
        gl.uniform1i(gl.getUniformLocation(program, name), units[j]);
      });
      var integer = kind === 'lattice';
      var rb = gl.createRenderbuffer();
      gl.bindRenderbuffer(gl.RENDERBUFFER, rb);
      gl.renderbufferStorage(gl.RENDERBUFFER, integer ? gl.RGBA32UI : gl.RGBA32F, w, h);
      var fb = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.RENDERBUFFER, rb);
      if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) throw new Error('float target incomplete');
      gl.viewport(0, 0, w, h);
      var passes = integer ? 5 : 1;
      for (var pass = 0; pass < passes; ++pass) {
        if (integer) gl.uniform1i(gl.getUniformLocation(program, 'q_what'), pass);
        gl.drawArrays(gl.TRIANGLES, 0, 3);
        var out = integer ? new Uint32Array(4 * w * h) : new Float32Array(4 * w * h);
        gl.readPixels(0, 0, w, h, integer ? gl.RGBA_INTEGER : gl.RGBA, integer ? gl.UNSIGNED_INT : gl.FLOAT, out);
        if (integer) results.debug.push(b64(out.buffer)); else results.rgb = b64(out.buffer);
      }
    });
    finish(gl, results);
  }).catch(fail);
})();
</script></body></html>
"""


@dataclass
class BrowserResult:
    """What the shader computed: ``rgb (N, 3)`` float32, the GL ``renderer`` string, and (lattice
    runs) ``vertices (N, 3, 2)`` int64, ``offsets (N, 3, 2)`` and ``texel (N, 2)`` int64."""

    rgb: np.ndarray
    renderer: str
    vertices: np.ndarray | None = None
    offsets: np.ndarray | None = None
    texel: np.ndarray | None = None


def _page_result(export_dir, kind: str, what: str, html: str, **run) -> str:
    """Run ``html`` as a temporary page in ``export_dir`` (its scripts' relative links resolve there) with
    :func:`run_page` options ``run``; return the text of its ``dynbtf-result`` element.

    An error the page shows in ``dynbtf-error``, or no result, raises ``RuntimeError`` naming the page.
    """
    fd, page = tempfile.mkstemp(prefix=f".dynbtf-{kind}-", suffix=".html", dir=export_dir)
    os.close(fd)
    page = Path(page)
    try:
        page.write_text(html, encoding="utf-8")
        result = run_page(page, **run)
    finally:
        page.unlink(missing_ok=True)
    error = result.element("dynbtf-error")
    if error:
        raise RuntimeError(f"the {what} page failed in Chromium: {error}")
    text = result.element("dynbtf-result")
    if not text:
        raise RuntimeError(f"the {what} page left no result (console: {result.console[-5:]})")
    return text


def _run_queries(export_dir, method: str, points, w_view, w_light, *, local_shift=None, lattice: bool = False,
                 gl: str = "swiftshader", timeout: float = 600.0) -> BrowserResult:
    export_dir = Path(export_dir)
    if not (export_dir / "manifest.js").is_file():
        raise InputError(f"{export_dir}: not a web export with its viewer files (manifest.js missing)")
    points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 2))
    n = len(points)
    wv = np.ascontiguousarray(np.asarray(w_view, dtype=np.float32).reshape(n, 3))
    wl = np.ascontiguousarray(np.asarray(w_light, dtype=np.float32).reshape(n, 3))
    shift = np.zeros(n, np.int32) if local_shift is None else np.asarray(local_shift, dtype=np.int32).reshape(n)
    width = min(max(n, 1), 256)
    job = {"n": n, "width": width, "method": method, "lattice": bool(lattice), "points": _b64(points),
           "shift": _b64(shift), "view": _b64(wv), "light": _b64(wl)}
    page = _QUERY_PAGE.replace("__HELPERS__", _PAGE_HELPERS).replace("__JOB__", json.dumps(job))
    text = _page_result(export_dir, "queries", "query", page,
                        gl=gl, timeout=timeout, budget_ms=600000)
    res = json.loads(text)
    rgb = np.frombuffer(base64.b64decode(res["rgb"]), dtype=np.float32).reshape(-1, 4)[:n, :3].copy()
    out = BrowserResult(rgb, res["renderer"])
    if lattice:
        d = [np.frombuffer(base64.b64decode(x), dtype=np.uint32).reshape(-1, 4)[:n].astype(np.uint64) for x in
             res["debug"]]

        def int64(lo, hi):
            return ((hi << np.uint64(32)) | lo).view(np.int64)

        out.vertices = np.stack([np.stack([int64(d[k][:, 0], d[k][:, 1]), int64(d[k][:, 2], d[k][:, 3])], -1)
                                 for k in range(3)], 1)
        off = np.stack([d[3][:, 0:2], d[3][:, 2:4], d[4][:, 0:2]], 1).astype(np.int64)
        out.offsets = off
        out.texel = d[4][:, 2:4].astype(np.int64)
    return out


def eval_in_browser(export_dir, method: str, points, w_view, w_light, *, local_shift=None, gl: str = "swiftshader",
                    timeout: float = 600.0) -> BrowserResult:
    """BTF values the exported shader computes in Chromium, ``rgb (N, 3)``.

    Parameters
    ----------
    export_dir : path
        A directory written by :func:`dynbtf.export.web.exporter.export_web` (with its viewer files).
    method : str
        One of the export's methods.
    points : ``(N, 2)`` float64
        Positions in exemplar repeats (the library's ``uv * scale``), split in the page in float64
        by ``DynBTF.origin``.
    w_view, w_light : ``(N, 3)``
        Unit directions in the local frame.
    local_shift : ``(N,)`` int, optional
        Whole repeats moved from the origin into the shader's float32 local uv (as a mesh's uv
        times the scale would be): exercises the shader's own lattice arithmetic.
    """
    return _run_queries(export_dir, method, points, w_view, w_light, local_shift=local_shift, gl=gl, timeout=timeout)


def lattice_in_browser(export_dir, method: str, points, *, local_shift=None, gl: str = "swiftshader",
                       timeout: float = 600.0) -> BrowserResult:
    """The shader's lattice triangle of each point: ``vertices (N, 3, 2)`` int64 and their hashed
    whole-texel ``offsets (N, 3, 2)`` (and ``rgb`` at normal view and light)."""
    n = len(np.asarray(points).reshape(-1, 2))
    up = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (n, 1))
    return _run_queries(export_dir, method, points, up, up, local_shift=local_shift, lattice=True, gl=gl,
                        timeout=timeout)


_LAYERED_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>dynbtf layered queries</title></head><body>
<pre id="dynbtf-result"></pre><pre id="dynbtf-error" hidden></pre>
<script src="viewer.js"></script>
<script>
(function () {
  var job = __JOB__;
__HELPERS__
  DynBTF.loadLayered('').then(function (data) {
    var n = job.n, w = job.width, h = Math.ceil(n / w), L = data.manifest;
    var points = new Float64Array(bytes(job.points)), view = new Float32Array(bytes(job.view));
    var light = new Float32Array(bytes(job.light));
    var gl = floatContext();
    var r = new DynBTF.LayeredRenderer(gl, data);
    // per query: the mask's origin from the whole uv units (float64 here), its local uv the rest (float32 there)
    var maskCell = new Uint32Array(4 * w * h), maskLocal = new Float32Array(4 * w * h);
    for (var i = 0; i < n; ++i) {
      var bu = Math.floor(points[2 * i]), bv = Math.floor(points[2 * i + 1]);
      var mo = DynBTF.maskOrigin(r.mask, bu, bv);
      maskCell.set(mo.cell, 4 * i);
      maskLocal.set([mo.offset[0], mo.offset[1], points[2 * i] - bu, points[2 * i + 1] - bv], 4 * i);
    }
    var vv = rows(view, n, w * h), ll = rows(light, n, w * h);
    var tex = texture(gl, w, h);
    var main = 'uniform highp usampler2D q_lattice; uniform highp isampler2D q_texel; uniform highp sampler2D q_local;\\n' +
      'uniform highp sampler2D q_view; uniform highp sampler2D q_light; uniform highp usampler2D q_mask_cell;\\n' +
      'uniform highp sampler2D q_mask_local; uniform highp sampler2D u_previous;\\n' +
      'layout(location = 0) out vec4 result;\\n' +
      'void main() { ivec2 p = ivec2(gl_FragCoord.xy);\\n' +
      '  DynbtfOrigin o; o.lattice = texelFetch(q_lattice, p, 0); o.phase = texelFetch(q_local, p, 0).x;\\n' +
      '  o.texel = texelFetch(q_texel, p, 0).xy; o.field = intBitsToFloat(texelFetch(q_texel, p, 0).zw);\\n' +
      '  vec4 m = texelFetch(q_mask_local, p, 0);\\n' +
      '  DynbtfMaskOrigin mo; mo.cell = texelFetch(q_mask_cell, p, 0); mo.offset = m.xy;\\n' +
      '  vec4 previous = dynbtf_layer_index == 1 ? texelFetch(u_previous, p, 0) : vec4(0.0);\\n' +
      '  result = dynbtf_layer_pass(o, texelFetch(q_local, p, 0).yz, mo, m.zw, texelFetch(q_view, p, 0).xyz,\\n' +
      '                             texelFetch(q_light, p, 0).xyz, previous); }\\n';
    var targets = [0, 1].map(function () { return floatTarget(gl, w, h); });
    var results = {passes: []};
    for (var k = 0; k < 2; ++k) {
      var layer = L.layers[k], m = data.layers[k].manifest, program = r.program(k, main);
      var q = origins(m, layer.method, n, w * h, function (i) {
        return [points[2 * i] * layer.scale, points[2 * i + 1] * layer.scale, 0];
      });
      r.use(program, k);
      if (k === 1) r.bindPrevious(targets[0].texture);
      var units = [5, 6, 7, 8, 9, 13, 14];
      tex(units[0], gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, q.lattice);
      tex(units[1], gl.RGBA32I, gl.RGBA_INTEGER, gl.INT, q.texel);
      tex(units[2], gl.RGBA32F, gl.RGBA, gl.FLOAT, q.local);
      tex(units[3], gl.RGBA32F, gl.RGBA, gl.FLOAT, vv);
      tex(units[4], gl.RGBA32F, gl.RGBA, gl.FLOAT, ll);
      tex(units[5], gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, maskCell);
      tex(units[6], gl.RGBA32F, gl.RGBA, gl.FLOAT, maskLocal);
      ['q_lattice', 'q_texel', 'q_local', 'q_view', 'q_light', 'q_mask_cell', 'q_mask_local'].forEach(function (name, j) {
        gl.uniform1i(gl.getUniformLocation(program, name), units[j]);
      });
      gl.bindFramebuffer(gl.FRAMEBUFFER, targets[k].fb);
      gl.viewport(0, 0, w, h);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      var out = new Float32Array(4 * w * h);
      gl.readPixels(0, 0, w, h, gl.RGBA, gl.FLOAT, out);
      results.passes.push(b64(out.buffer));
    }
    finish(gl, results);
  }).catch(fail);
})();
</script></body></html>
"""


@dataclass
class LayeredBrowserResult:
    """What a layered export's shader computed: ``rgb (N, 3)`` (the mix), layer 0's pass ``first (N, 4)`` (its value
    and height, zero where it cannot show) and ``weight (N,)`` (layer 1's)."""

    rgb: np.ndarray
    first: np.ndarray
    weight: np.ndarray


def eval_layered_in_browser(export_dir, uv, w_view, w_light, *, gl: str = "swiftshader",
                            timeout: float = 600.0) -> LayeredBrowserResult:
    """Values of a layered export (:func:`dynbtf.export.web.layered.export_layered_web`) in Chromium.

    ``uv (N, 2)`` float64 in the surface's units (the library's ``LayeredBTF.eval`` input): each layer's
    position is ``uv x scale`` split by ``DynBTF.origin``; the mask's origin is the whole uv units (split by
    ``DynBTF.maskOrigin``) and its float32 local uv the rest, so the shader's own addition is exercised.
    """
    export_dir = Path(export_dir)
    if not (export_dir / "layered.js").is_file():
        raise InputError(f"{export_dir}: not a layered web export with its viewer files (layered.js missing)")
    uv = np.ascontiguousarray(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    n = len(uv)
    wv = np.ascontiguousarray(np.asarray(w_view, dtype=np.float32).reshape(n, 3))
    wl = np.ascontiguousarray(np.asarray(w_light, dtype=np.float32).reshape(n, 3))
    job = {"n": n, "width": min(max(n, 1), 256), "points": _b64(uv), "view": _b64(wv), "light": _b64(wl)}
    page = _LAYERED_PAGE.replace("__HELPERS__", _PAGE_HELPERS).replace("__JOB__", json.dumps(job))
    text = _page_result(export_dir, "layered", "layered query", page,
                        gl=gl, timeout=timeout, budget_ms=600000)
    passes = [np.frombuffer(base64.b64decode(x), dtype=np.float32).reshape(-1, 4)[:n].copy()
              for x in json.loads(text)["passes"]]
    return LayeredBrowserResult(passes[1][:, :3], passes[0], passes[1][:, 3])


_FRAME_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>dynbtf frame time</title></head><body>
<pre id="dynbtf-result"></pre><pre id="dynbtf-error"></pre>
<script src="viewer.js"></script>
__SCRIPTS__
<script>
(function () {
  var job = __JOB__;
  try {
    var data = DynBTF.collect(), m = data.manifest;
    var canvas = document.createElement('canvas');
    canvas.width = job.width; canvas.height = job.height;
    var gl = canvas.getContext('webgl2', {antialias: false});
    if (!gl) throw new Error('no WebGL2');
    var dbg = gl.getExtension('WEBGL_debug_renderer_info');
    var out = {renderer: dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER),
               width: job.width, height: job.height, methods: {}};
    var r = new DynBTF.Renderer(gl, data);
    // a camera looking down at the plane: uv across the frame, view directions of a 60 deg field of view
    var t0 = performance.now();
    var program = r.program(
      'uniform uvec4 u_lattice; uniform float u_phase; uniform ivec2 u_texel; uniform vec2 u_fraction;\\n' +
      'uniform vec2 u_field; uniform vec2 u_size; uniform float u_scale; uniform vec3 u_light; out vec4 color;\\n' +
      'void main() { vec2 s = gl_FragCoord.xy / u_size; DynbtfOrigin o; o.lattice = u_lattice; o.phase = u_phase;\\n' +
      '  o.texel = u_texel; o.field = u_field; vec2 local = u_fraction + vec2(s.x * u_size.x / u_size.y, s.y) * u_scale;\\n' +
      '  vec3 wv = normalize(vec3((s - 0.5) * vec2(u_size.x / u_size.y, 1.0) * 1.15, 1.0));\\n' +
      '  vec3 v = dynbtf_eval(o, local, wv, u_light) * u_light.z;\\n' +
      '  color = vec4(pow(clamp(v, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0); }\\n');
    out.compile_ms = performance.now() - t0;
    var pixel = new Uint8Array(4);
    job.methods.forEach(function (name) {
      r.use(program, name);
      var o = DynBTF.origin(m, name, job.origin, job.origin);
      function u(n) { return gl.getUniformLocation(program, n); }
      gl.uniform4ui(u('u_lattice'), o.lattice[0], o.lattice[1], o.lattice[2], o.lattice[3]);
      gl.uniform1f(u('u_phase'), o.phase);
      gl.uniform2i(u('u_texel'), o.texel[0], o.texel[1]);
      gl.uniform2f(u('u_fraction'), o.fraction[0], o.fraction[1]);
      gl.uniform2f(u('u_field'), o.field[0], o.field[1]);
      gl.uniform2f(u('u_size'), job.width, job.height);
      gl.uniform1f(u('u_scale'), job.scale);
      gl.uniform3f(u('u_light'), 0.45, 0.2, Math.sqrt(1 - 0.45 * 0.45 - 0.2 * 0.2));
      gl.viewport(0, 0, job.width, job.height);
      var times = [];
      for (var f = 0; f < job.frames + 1; ++f) {  // the first frame (warm-up: shader variants, uploads) is not counted
        var start = performance.now();
        gl.drawArrays(gl.TRIANGLES, 0, 3);
        gl.readPixels(job.width >> 1, job.height >> 1, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);  // waits for the frame
        if (f > 0) times.push(performance.now() - start);
      }
      out.methods[name] = {frame_ms: times, center_pixel: Array.prototype.slice.call(pixel)};
    });
    if (gl.getError() !== gl.NO_ERROR) throw new Error('WebGL error');
    document.getElementById('dynbtf-result').textContent = JSON.stringify(out);
  } catch (e) {
    document.getElementById('dynbtf-error').textContent = String(e && e.message || e);
  }
})();
</script></body></html>
"""


_LAYERED_FRAME_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>dynbtf layered frame time</title></head><body>
<pre id="dynbtf-result"></pre><pre id="dynbtf-error"></pre>
<script src="viewer.js"></script>
<script>
(function () {
__HELPERS__
  var job = __JOB__;
  DynBTF.loadLayered('').then(function (data) {
    var L = data.manifest, w = job.width, h = job.height;
    var canvas = document.createElement('canvas');
    canvas.width = w; canvas.height = h;
    var gl = canvas.getContext('webgl2', {antialias: false});
    if (!gl) throw new Error('no WebGL2');
    if (!gl.getExtension('EXT_color_buffer_float')) throw new Error('no EXT_color_buffer_float');
    var dbg = gl.getExtension('WEBGL_debug_renderer_info');
    var out = {renderer: dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER),
               width: w, height: h, frame_ms: {}};
    var r = new DynBTF.LayeredRenderer(gl, data);
    // the plane seen from above, span uv units across the frame's height; the mask's origin at 0
    var frame = 'uniform uvec4 u_lattice; uniform float u_phase; uniform ivec2 u_texel; uniform vec2 u_fraction;\\n' +
      'uniform vec2 u_size; uniform float u_scale; uniform float u_span; uniform vec3 u_light;\\n' +
      'uniform highp sampler2D u_previous; out vec4 color;\\n' +
      'void setup(out DynbtfOrigin o, out vec2 local, out vec2 mask, out vec3 wv) { vec2 s = gl_FragCoord.xy / u_size;\\n' +
      '  vec2 a = vec2(s.x * u_size.x / u_size.y, s.y); o.lattice = u_lattice; o.phase = u_phase; o.texel = u_texel;\\n' +
      '  local = u_fraction + a * u_scale; mask = a * u_span;\\n' +
      '  wv = normalize(vec3((s - 0.5) * vec2(u_size.x / u_size.y, 1.0) * 1.15, 1.0)); }\\n';
    var alone = frame + 'void main() { DynbtfOrigin o; vec2 local, mask; vec3 wv; setup(o, local, mask, wv);\\n' +
      '  color = vec4(dynbtf_eval(o, local, wv, u_light), 1.0); }\\n';
    var pass = frame + 'void main() { DynbtfOrigin o; vec2 local, mask; vec3 wv; setup(o, local, mask, wv);\\n' +
      '  DynbtfMaskOrigin mo; mo.cell = uvec4(0u); mo.offset = vec2(0.0);\\n' +
      '  vec4 previous = dynbtf_layer_index == 1 ? texelFetch(u_previous, ivec2(gl_FragCoord.xy), 0) : vec4(0.0);\\n' +
      '  color = dynbtf_layer_pass(o, local, mo, mask, wv, u_light, previous); }\\n';
    var light = [0.45, 0.2, Math.sqrt(1 - 0.45 * 0.45 - 0.2 * 0.2)];
    var layer0 = floatTarget(gl, w, h), target = layer0.texture, fb = layer0.fb;  // layer 0's pass draws here
    gl.viewport(0, 0, w, h);
    function set(program, k) {
      var layer = L.layers[k], m = data.layers[k].manifest;
      var o = DynBTF.origin(m, layer.method, 0, 0);
      function u(n) { return gl.getUniformLocation(program, n); }
      gl.uniform4ui(u('u_lattice'), o.lattice[0], o.lattice[1], o.lattice[2], o.lattice[3]);
      gl.uniform1f(u('u_phase'), o.phase);
      gl.uniform2i(u('u_texel'), o.texel[0], o.texel[1]);
      gl.uniform2f(u('u_fraction'), o.fraction[0], o.fraction[1]);
      gl.uniform2f(u('u_size'), w, h);
      gl.uniform1f(u('u_scale'), job.span * layer.scale);
      gl.uniform1f(u('u_span'), job.span);
      gl.uniform3f(u('u_light'), light[0], light[1], light[2]);
    }
    var pixel = new Float32Array(4), bytes = new Uint8Array(4);
    function time(draw, read) {  // frames + 1 frames, the first (warm-up) not counted; each waits for its pixels
      var times = [];
      for (var f = 0; f < job.frames + 1; ++f) {
        var start = performance.now();
        draw();
        read();
        if (f > 0) times.push(performance.now() - start);
      }
      return times;
    }
    [0, 1].forEach(function (k) {  // each layer alone, one pass as the single viewer draws it
      var program = r.layers[k].program(alone);
      r.layers[k].use(program, L.layers[k].method);
      set(program, k);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      out.frame_ms['layer ' + k + ' alone'] = time(function () { gl.drawArrays(gl.TRIANGLES, 0, 3); },
        function () { gl.readPixels(w >> 1, h >> 1, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, bytes); });
    });
    var programs = [r.program(0, pass), r.program(1, pass)];
    out.frame_ms.layered = time(function () {  // as the viewer draws it: layer 0 into a float target, then layer 1
      for (var k = 0; k < 2; ++k) {
        gl.bindFramebuffer(gl.FRAMEBUFFER, k === 0 ? fb : null);
        r.use(programs[k], k);
        if (k === 1) r.bindPrevious(target);
        set(programs[k], k);
        gl.drawArrays(gl.TRIANGLES, 0, 3);
      }
    }, function () { gl.readPixels(w >> 1, h >> 1, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, bytes); });
    if (gl.getError() !== gl.NO_ERROR) throw new Error('WebGL error ' + gl.getError());
    document.getElementById('dynbtf-result').textContent = JSON.stringify(out);
  }).catch(function (e) { document.getElementById('dynbtf-error').textContent = String(e && e.message || e); });
})();
</script></body></html>
"""


def time_layered_frames(export_dir, *, width: int = 1280, height: int = 720, frames: int = 3, span: float = 1.0,
                        gl: str = "gpu", timeout: float = 1800.0) -> FrameTimes:
    """Frame times of a layered export (:func:`dynbtf.export.web.layered.export_layered_web`) in headless Chromium:
    each layer alone (one full-screen pass of its ``dynbtf_eval``) and the layered material as the viewer draws it
    (layer 0's pass into a float target, then layer 1's), the plane seen from above with ``span`` uv units across the frame's height and the
    export's mask. ``frame_ms`` keys: ``"layer 0 alone"``, ``"layer 1 alone"``, ``"layered"``."""
    export_dir = Path(export_dir)
    if not (export_dir / "layered.js").is_file():
        raise InputError(f"{export_dir}: not a layered web export with its viewer files (layered.js missing)")
    job = {"width": int(width), "height": int(height), "frames": int(frames), "span": float(span)}
    res = json.loads(_page_result(export_dir, "layered-frames", "layered frame-time",
                                  _LAYERED_FRAME_PAGE.replace("__HELPERS__", _PAGE_HELPERS).replace("__JOB__", json.dumps(job)), gl=gl, timeout=timeout,
                                  budget_ms=None, window=(width, height)) or "{}")
    if not res:
        raise RuntimeError("the layered frame-time page left an empty result")
    return FrameTimes(res["renderer"], res["width"], res["height"], res["frame_ms"], 0.0)


@dataclass
class FrameTimes:
    """Frame times (ms) per method at ``width x height``, the GL ``renderer`` string and the program's compile time."""

    renderer: str
    width: int
    height: int
    frame_ms: dict[str, list[float]]
    compile_ms: float

    @property
    def software(self) -> bool:
        """Whether the browser rendered with a software GL (SwiftShader / llvmpipe)."""
        return any(s in self.renderer for s in ("SwiftShader", "llvmpipe", "Software"))


def time_frames(export_dir, methods=None, *, width: int = 1280, height: int = 720, frames: int = 3,
                scale: float = 8.0, origin: float = 0.0, gl: str = "gpu", timeout: float = 1800.0,
                extra_flags: tuple[str, ...] = ()) -> FrameTimes:
    """Time full frames of the exported shader in headless Chromium (every pixel one ``dynbtf_eval``).

    Each frame draws one full-screen pass into a ``width x height`` canvas and waits for it
    (a one-pixel ``readPixels``); the first frame of each method is a warm-up and not counted.
    ``gl="gpu"`` uses the machine's GPU when Chromium finds one (else SwiftShader), ``"swiftshader"``
    forces software GL; ``extra_flags`` are passed to Chromium (:func:`run_page`).
    """
    export_dir = Path(export_dir)
    manifest_path = export_dir / "manifest.json"
    if not (export_dir / "manifest.js").is_file() or not manifest_path.is_file():
        raise InputError(f"{export_dir}: not a web export with its viewer files (manifest.js missing)")
    manifest = json.loads(manifest_path.read_text())
    methods = list(methods or manifest["methods"])
    scripts = "\n".join(f'<script src="{name}"></script>' for name in
                        ["manifest.js", *(f"{f}.js" for f in manifest["files"])])
    job = {"width": int(width), "height": int(height), "frames": int(frames), "methods": methods,
           "scale": float(scale), "origin": float(origin)}
    res = json.loads(_page_result(export_dir, "frames", "frame-time",
                                  _FRAME_PAGE.replace("__SCRIPTS__", scripts).replace("__JOB__", json.dumps(job)),
                                  gl=gl, timeout=timeout, budget_ms=None, window=(width, height),
                                  extra_flags=extra_flags)) or {}
    if not res:
        raise RuntimeError("the frame-time page left an empty result")
    return FrameTimes(res["renderer"], res["width"], res["height"],
                      {k: v["frame_ms"] for k, v in res["methods"].items()}, res["compile_ms"])
