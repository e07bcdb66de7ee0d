"""report.html's static parts: the page template, its style sheet and its script (which draws the plots and the 3D
views from the page's JSON data, sorts the table, selects a defect region, and reports its own state in
``window.reportStatus`` for the headless-browser test). Filled in by :mod:`inspection.html_report`."""

EMPHASIS = 3.0  # patch residual above which a point is drawn larger (3 standard deviations)

STATUS_HEAD = """<script>
window.reportStatus = {ready: false, errors: [], plots: {}};
window.onerror = function (msg, src, line, col, err) {
  window.reportStatus.errors.push(String(msg) + (line ? " (line " + line + ")" : ""));
};
window.addEventListener("unhandledrejection", function (e) {
  window.reportStatus.errors.push("unhandled rejection: " + String(e.reason));
});
</script>"""

STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0; color: #212121; }
header { background: #263238; color: #fff; padding: 14px 24px; }
header h1 { margin: 0 0 6px 0; font-size: 22px; }
header .verdicts { font-size: 18px; }
header .sub { font-size: 12px; color: #cfd8dc; margin-top: 6px; }
.pill { display: inline-block; padding: 2px 10px; border-radius: 12px; color: #fff; font-weight: 600;
        margin-right: 4px; }
section { padding: 6px 24px 12px 24px; }
h2 { font-size: 18px; border-bottom: 1px solid #cfd8dc; padding-bottom: 4px; }
.note { color: #546e7a; font-size: 13px; }
.warn { background: #fff3e0; border-left: 4px solid #ef6c00; padding: 6px 10px; }
.plots { display: flex; flex-wrap: wrap; gap: 12px; }
.plot { flex: 1 1 460px; min-width: 360px; }
.view3d { width: 100%; height: 560px; border: 1px solid #cfd8dc; }
.viewer-bar { margin-bottom: 8px; }
.viewer-bar select { font-size: 14px; max-width: 60%; }
#scan-info { margin-left: 12px; font-size: 14px; }
table { border-collapse: collapse; font-size: 13px; }
#verdict-table th { cursor: pointer; background: #eceff1; user-select: none; }
#verdict-table th.asc::after { content: " \\25B2"; } #verdict-table th.desc::after { content: " \\25BC"; }
th, td { padding: 3px 10px; border-bottom: 1px solid #eceff1; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.verdict { font-weight: 600; }
tr.v-defective { background: #ffebee; } tr.v-uncertain { background: #fff3e0; } tr.v-error { background: #efebe9; }
table.kv th { background: none; font-weight: 600; }
#report-status { display: none; }
"""

SCRIPT = """
(function () {
  var S = window.reportStatus;
  var D = JSON.parse(document.getElementById("report-data").textContent);
  var CONFIG = {displaylogo: false, responsive: true};
  function bytes(b64) {
    var s = atob(b64), u = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
    return u.buffer;
  }
  function f32(b64) { return new Float32Array(bytes(b64)); }
  function column(xyz, c) {
    var out = new Float32Array(xyz.length / 3);
    for (var i = 0; i < out.length; i++) out[i] = xyz[3 * i + c];
    return out;
  }
  function cloud(xyz, v, emph, range, label, scene, bar_x) {
    // two traces: the points at or below the emphasis threshold, and those above it, drawn larger on top
    var n = v.length, lo = [], hi = [];
    for (var i = 0; i < n; i++) (v[i] > emph ? hi : lo).push(i);
    function part(idx, size, name, scale) {
      var x = new Float32Array(idx.length), y = new Float32Array(idx.length), z = new Float32Array(idx.length),
          c = new Float32Array(idx.length);
      idx.forEach(function (j, k) { x[k] = xyz[3 * j]; y[k] = xyz[3 * j + 1]; z[k] = xyz[3 * j + 2]; c[k] = v[j]; });
      return {type: "scatter3d", mode: "markers", name: name, scene: scene, showlegend: false, x: x, y: y, z: z,
              marker: {size: size, color: c, colorscale: D.scale.colorscale, cmin: range[0], cmax: range[1],
                       showscale: scale, opacity: 1,
                       colorbar: {title: {text: label, side: "right"}, x: bar_x, len: 0.8, thickness: 14}},
              hovertemplate: "%{marker.color:.2f}<extra>" + name + "</extra>"};
    }
    return [part(lo, 2, "points", true), part(hi, 5, "emphasised", false)];
  }
  var current = 0, drawn3d = false;
  function viewLayout(rays) {
    var axis = {showticklabels: false, title: {text: ""}, showbackground: true, backgroundcolor: "#f5f5f5"};
    var scene = {aspectmode: "data", xaxis: axis, yaxis: axis, zaxis: axis};
    var layout = {margin: {l: 0, r: 0, t: 30, b: 0}, uirevision: "keep", showlegend: false,
                  scene: Object.assign({domain: {x: rays ? [0, 0.46] : [0, 0.9], y: [0, 1]}}, scene)};
    if (rays) layout.scene2 = Object.assign({domain: {x: [0.52, 0.96], y: [0, 1]}}, scene);
    if (rays) layout.annotations = [
      {text: "anomaly map", showarrow: false, x: 0.2, y: 1.0, xref: "paper", yref: "paper"},
      {text: "ray map", showarrow: false, x: 0.74, y: 1.0, xref: "paper", yref: "paper"}];
    return layout;
  }
  function regionTrace(xyz, ids, region) {
    // the selected defect region's points, large and magenta, over the map
    var x = [], y = [], z = [];
    for (var i = 0; i < ids.length; i++) if (ids[i] === region) {
      x.push(xyz[3 * i]); y.push(xyz[3 * i + 1]); z.push(xyz[3 * i + 2]);
    }
    return {type: "scatter3d", mode: "markers", name: "region " + region, scene: "scene", showlegend: false,
            x: x, y: y, z: z, marker: {size: 7, color: "#e040fb", opacity: 0.55},
            hovertemplate: "region " + region + "<extra></extra>"};
  }
  function showScan(i, region) {
    var el = document.getElementById("view3d");
    if (!el || !D.views.length) return Promise.resolve();
    current = (i + D.views.length) % D.views.length;
    var v = D.views[current];
    document.getElementById("scan-select").value = String(current);
    document.getElementById("scan-info").textContent = v.k.toLocaleString() + " of " + v.n.toLocaleString() +
      " points shown, " + v.hot + " above " + %(emphasis)s + " sd";
    var rays = !!v.r, xyz = f32(v.xyz);
    var traces = cloud(xyz, f32(v.v), D.scale.emphasis, D.scale.range, "patch residual (sd)", "scene", rays ? 0.47 : 0.92);
    if (rays) traces = traces.concat(cloud(xyz, f32(v.r), D.scale.ray_emphasis, D.scale.ray_range, "P(blocked)",
                                           "scene2", 0.97));
    var selected = null;
    if (region !== undefined && region !== null && v.g) {
      var ids = new Int16Array(bytes(v.g)), t = regionTrace(xyz, ids, region);
      if (t.x.length) { traces.push(t); selected = {region: region, points: t.x.length}; }
    }
    var layout = viewLayout(rays);
    layout.title = {text: v.name + (selected ? " - region " + region : ""), font: {size: 14}};
    return Plotly.react(el, traces, layout, CONFIG).then(function (gd) {
      return new Promise(function (resolve) {
        requestAnimationFrame(function () { requestAnimationFrame(function () {
          var sc = gd._fullLayout.scene && gd._fullLayout.scene._scene, gl = sc && sc.glplot && sc.glplot.gl;
          S.plots.view3d = {traces: gd.data.length, scan: v.name, canvases: gd.querySelectorAll("canvas").length,
                            webgl: !!(gl && !gl.isContextLost() && gl.drawingBufferWidth > 0),
                            objects: sc && sc.glplot ? sc.glplot.objects.length : 0, points: v.k,
                            region: selected ? selected.region : null,
                            region_points: selected ? selected.points : 0};
          drawn3d = true;
          resolve(gd);
        }); });
      });
    });
  }
  var promises = [];
  Object.keys(D.figures).forEach(function (k) {
    var fig = D.figures[k], el = document.getElementById("plot-" + k);
    promises.push(Plotly.newPlot(el, fig.data, fig.layout, CONFIG).then(function (gd) {
      S.plots[k] = {traces: gd.data.length, svg: gd.querySelectorAll("svg.main-svg").length};
    }));
  });
  if (D.views.length) {
    // #region=<scan>|<id> in the page's address selects a defect region, as a click on its row does
    var wanted = /^#region=(.*)\\|(-?\\d+)$/.exec(decodeURIComponent(window.location.hash || ""));
    var first = wanted && D.view_of[wanted[1]] !== undefined ? D.view_of[wanted[1]] : 0;
    promises.push(showScan(first, wanted && D.view_of[wanted[1]] !== undefined ? +wanted[2] : null));
    document.querySelectorAll("a.region3d").forEach(function (a) {
      a.addEventListener("click", function () {
        showScan(D.view_of[a.getAttribute("data-name")], +a.getAttribute("data-region"));
      });
    });
    document.getElementById("scan-select").addEventListener("change", function (e) { showScan(+e.target.value); });
    document.getElementById("prev").addEventListener("click", function () { showScan(current - 1); });
    document.getElementById("next").addEventListener("click", function () { showScan(current + 1); });
    document.querySelectorAll("a.show3d").forEach(function (a) {
      a.addEventListener("click", function () { showScan(D.view_of[a.getAttribute("data-name")]); });
    });
  }
  // sortable table: click a heading; numbers by data-sort, text by content
  var table = document.getElementById("verdict-table");
  if (table) table.querySelectorAll("th").forEach(function (th) {
    th.addEventListener("click", function () {
      var col = +th.getAttribute("data-col"), num = th.getAttribute("data-type") === "num";
      var asc = !th.classList.contains("asc");
      table.querySelectorAll("th").forEach(function (h) { h.classList.remove("asc", "desc"); });
      th.classList.add(asc ? "asc" : "desc");
      var body = table.tBodies[0], rows = Array.prototype.slice.call(body.rows);
      rows.sort(function (a, b) {
        var x = a.cells[col], y = b.cells[col], r;
        if (num) {
          var p = x.hasAttribute("data-sort") ? +x.getAttribute("data-sort") : -Infinity;
          var q = y.hasAttribute("data-sort") ? +y.getAttribute("data-sort") : -Infinity;
          r = p - q;
        } else r = x.textContent.localeCompare(y.textContent);
        return asc ? r : -r;
      });
      rows.forEach(function (r) { body.appendChild(r); });
    });
  });
  Promise.all(promises).then(function () {
    S.ready = true;
    S.views = D.views.length;
  }, function (err) {
    S.errors.push("plot failed: " + String(err));
  }).then(function () {
    document.getElementById("report-status").textContent = JSON.stringify(S);
  });
})();
""".replace("%(emphasis)s", repr(EMPHASIS))

PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>{style}</style>
{status_head}
<script>{plotly}</script>
</head>
<body>
{body}
<pre id="report-status"></pre>
<script type="application/json" id="report-data">{data}</script>
<script>{script}</script>
</body>
</html>
"""
