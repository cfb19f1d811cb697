"""The report's image comparator: one viewer that flips between a technique's image and the truth.

Pure HTML, CSS and JavaScript in the page itself (no server, no external files, works from
``file://``). The page holds an empty ``<div id="cmp">`` and the data as JSON
(``<script type="application/json" id="cmp-data">``); the script builds the viewer when the page
loads:

* a choice of technique (every technique, and Mitsuba's ``mi.render`` against the truth's shaded
  image) and of image (the shaded image, each light's visibility);
* four modes: the technique, the truth, the difference |technique − truth| and the signed error
  map (the report's heat map, with its colour bar and scale). The difference is computed by the
  browser (CSS ``mix-blend-mode: difference``) on the displayed 8-bit values (sRGB for shaded
  images, the visibility itself for visibility images), times a gain of 1, 4 or 16;
* flipping by key (Space or T: technique ⇄ truth; 1–4 pick a mode) or by hover (pointing at a
  mode button shows that mode while the pointer stays; "flip on hover" shows the truth while the
  pointer is on the image);
* zoom with nearest-neighbour pixels (CSS ``image-rendering: pixelated``): + / − keys, the mouse
  wheel over the image (around the pointer), drag to pan, 0 to fit; the status line gives the
  pixel under the pointer.

Keys act when no text field or menu has the focus; ← / → pick the technique, ↑ / ↓ the image.
The images are the report's own PNGs (img/…), so the viewer adds no files.

>>> html = comparator_html({"width": 8, "height": 8, "items": []})
>>> 'id="cmp"' in html and 'id="cmp-data"' in html
True
"""

from __future__ import annotations

import json

__all__ = ["comparator_html", "item", "layer", "CSS"]


def layer(label: str, a: str, b: str, err: str, scale: str) -> dict:
    """One image of an item: its technique PNG ``a``, truth PNG ``b``, signed error map ``err``
    (paths relative to the page) and the error map's scale (text, e.g. "0.05")."""
    return {"label": label, "a": a, "b": b, "err": err, "scale": scale}


def item(name: str, layers: list[dict], a_label: str = "technique", b_label: str = "truth") -> dict:
    """One entry of the technique menu: a name and its images (:func:`layer`)."""
    return {"name": name, "layers": layers, "a_label": a_label, "b_label": b_label}


CSS = """
#cmp { margin: .5em 0 1em; }
#cmp .cmp-bar { display: flex; flex-wrap: wrap; gap: .4em .8em; align-items: center; margin-bottom: .4em; font-size: .9em; }
#cmp .cmp-modes button { font: inherit; padding: 2px 9px; border: 1px solid #999; background: #f4f4f4; cursor: pointer; }
#cmp .cmp-modes button.on { background: #2166ac; color: #fff; border-color: #2166ac; }
#cmp-viewport { max-width: 1024px; max-height: 640px; overflow: auto; border: 1px solid #bbb; background: #777;
  display: inline-block; cursor: crosshair; vertical-align: top; }
#cmp-stack { position: relative; isolation: isolate; }
#cmp-stack img { position: absolute; left: 0; top: 0; width: 100%; height: 100%; image-rendering: crisp-edges;
  image-rendering: pixelated; display: block; user-select: none; -webkit-user-drag: none; }
#cmp-stack.diff #cmp-a { mix-blend-mode: difference; }
#cmp .cmp-side { display: inline-block; vertical-align: top; margin-left: 1em; font-size: .85em; max-width: 22em; }
#cmp-legend .cbar { width: 256px; height: 10px; background: linear-gradient(to right, rgb(33,102,172), #fff, rgb(178,24,43)); }
#cmp-legend .ticks { width: 256px; display: flex; justify-content: space-between; }
#cmp-status { font-variant-numeric: tabular-nums; color: #333; margin-top: .3em; }
#cmp kbd { border: 1px solid #bbb; border-radius: 3px; padding: 0 3px; font-size: .9em; background: #fafafa; }
"""  # noqa: E501

_JS = r"""
(function () {
  "use strict";
  var root = document.getElementById("cmp");
  var src = document.getElementById("cmp-data");
  if (!root || !src) { return; }
  var data = JSON.parse(src.textContent);
  if (!data.items.length) { root.textContent = "No images to compare."; return; }
  var W = data.width, H = data.height;
  var MODES = [["a", "technique", "1"], ["b", "truth", "2"], ["diff", "difference", "3"], ["err", "error map", "4"]];
  var ZOOMS = [1, 2, 3, 4, 6, 8, 12, 16, 24, 32];
  var st = {item: 0, layer: 0, mode: "a", preview: null, zoom: 0, gain: 4, hover: false};

  function el(tag, attrs, parent) {
    var e = document.createElement(tag);
    Object.keys(attrs || {}).forEach(function (k) {
      if (k === "text") { e.textContent = attrs[k]; } else { e.setAttribute(k, attrs[k]); }
    });
    if (parent) { parent.appendChild(e); }
    return e;
  }

  var bar = el("div", {"class": "cmp-bar"}, root);
  var itemSel = el("select", {id: "cmp-item", "aria-label": "technique"}, bar);
  var layerSel = el("select", {id: "cmp-layer", "aria-label": "image"}, bar);
  var modes = el("span", {"class": "cmp-modes"}, bar);
  var modeBtn = {};
  MODES.forEach(function (m) {
    var b = el("button", {type: "button", "data-mode": m[0], title: "key " + m[2], text: m[1]}, modes);
    modeBtn[m[0]] = b;
    b.addEventListener("click", function () { setMode(m[0]); });
    b.addEventListener("mouseenter", function () { st.preview = m[0]; show(); });
    b.addEventListener("mouseleave", function () { st.preview = null; show(); });
  });
  var gainSel = el("select", {id: "cmp-gain", "aria-label": "difference gain", title: "gain of the difference"}, bar);
  [1, 4, 16].forEach(function (g) { el("option", {value: String(g), text: "×" + g}, gainSel); });
  gainSel.value = String(st.gain);
  var zoomOut = el("button", {type: "button", id: "cmp-zoom-out", title: "key −", text: "−"}, bar);
  var zoomLabel = el("span", {id: "cmp-zoom"}, bar);
  var zoomIn = el("button", {type: "button", id: "cmp-zoom-in", title: "key +", text: "+"}, bar);
  var zoomFit = el("button", {type: "button", id: "cmp-zoom-fit", title: "key 0", text: "fit"}, bar);
  var hoverLab = el("label", {title: "show the truth while the pointer is on the image"}, bar);
  var hoverBox = el("input", {type: "checkbox", id: "cmp-hover"}, hoverLab);
  hoverLab.appendChild(document.createTextNode(" flip on hover"));

  var view = el("div", {id: "cmp-viewport", tabindex: "0"}, root);
  var stack = el("div", {id: "cmp-stack"}, view);
  var imgB = el("img", {id: "cmp-b", alt: "truth", draggable: "false"}, stack);
  var imgA = el("img", {id: "cmp-a", alt: "technique", draggable: "false"}, stack);
  var imgE = el("img", {id: "cmp-err", alt: "signed error", draggable: "false"}, stack);
  var side = el("div", {"class": "cmp-side"}, root);
  var title = el("div", {id: "cmp-title"}, side);
  var legendBox = el("div", {id: "cmp-legend"}, side);
  var status = el("div", {id: "cmp-status"}, side);
  el("p", {"class": "note", text: "Keys: Space or T flips technique ⇄ truth; 1 technique, 2 truth, 3 difference, " +
    "4 error map; + / − zoom (or the wheel over the image), 0 fits; ← → technique, ↑ ↓ image. Point at a mode " +
    "button to see that mode; drag to pan."}, side);

  data.items.forEach(function (it, i) { el("option", {value: String(i), text: it.name}, itemSel); });

  function cur() { return data.items[st.item]; }
  function lay() { return cur().layers[st.layer]; }

  function fillLayers() {
    layerSel.textContent = "";
    cur().layers.forEach(function (l, i) { el("option", {value: String(i), text: l.label}, layerSel); });
    st.layer = Math.min(st.layer, cur().layers.length - 1);
    layerSel.value = String(st.layer);
  }

  function fitZoom() {
    var w = Math.max(view.parentNode.clientWidth - 360, 256);
    var z = ZOOMS.filter(function (k) { return W * k <= Math.min(w, 1024) && H * k <= 640; });
    return z.length ? ZOOMS.indexOf(z[z.length - 1]) : 0;
  }

  function layout() {
    var z = ZOOMS[st.zoom];
    stack.style.width = (W * z) + "px";
    stack.style.height = (H * z) + "px";
    view.style.width = Math.min(W * z, 1024) + 2 + "px";
    view.style.height = Math.min(H * z, 640) + 2 + "px";
    zoomLabel.textContent = z + "×";
  }

  function legend(mode) {
    legendBox.textContent = "";
    var it = cur(), l = lay();
    if (mode === "err") {
      el("div", {text: "signed error (" + it.a_label + " − " + it.b_label + "): blue darker, red brighter"}, legendBox);
      el("div", {"class": "cbar"}, legendBox);
      var t = el("div", {"class": "ticks"}, legendBox);
      ["−" + l.scale, "0", "+" + l.scale].forEach(function (s) { el("span", {text: s}, t); });
    } else if (mode === "diff") {
      el("div", {text: "|" + it.a_label + " − " + it.b_label + "| of the displayed values, ×" + st.gain +
        " (black: equal)"}, legendBox);
    }
  }

  function show() {
    var mode = st.preview || st.mode;
    if (st.hover && st.inside && !st.preview) { mode = (mode === "b") ? "a" : "b"; }
    var it = cur(), l = lay();
    if (imgA.getAttribute("src") !== l.a) { imgA.setAttribute("src", l.a); }
    if (imgB.getAttribute("src") !== l.b) { imgB.setAttribute("src", l.b); }
    if (imgE.getAttribute("src") !== l.err) { imgE.setAttribute("src", l.err); }
    imgA.style.visibility = (mode === "a" || mode === "diff") ? "visible" : "hidden";
    imgB.style.visibility = (mode === "b" || mode === "diff") ? "visible" : "hidden";
    imgE.style.visibility = (mode === "err") ? "visible" : "hidden";
    stack.className = (mode === "diff") ? "diff" : "";
    stack.style.filter = (mode === "diff" && st.gain !== 1) ? "brightness(" + st.gain + ")" : "";
    Object.keys(modeBtn).forEach(function (k) { modeBtn[k].className = (k === st.mode) ? "on" : ""; });
    var names = {a: it.a_label, b: it.b_label, diff: "difference", err: "error map"};
    title.textContent = it.name + " · " + l.label + " · showing: " + names[mode];
    root.setAttribute("data-mode", mode);
    legend(mode);
    layout();
  }

  function setMode(m) { st.mode = m; st.preview = null; show(); }
  function setItem(i) {
    st.item = (i + data.items.length) % data.items.length;
    itemSel.value = String(st.item);
    fillLayers();
    show();
  }
  function setLayer(i) {
    var n = cur().layers.length;
    st.layer = (i + n) % n;
    layerSel.value = String(st.layer);
    show();
  }
  function zoomTo(k, cx, cy) {
    k = Math.max(0, Math.min(ZOOMS.length - 1, k));
    if (cx === undefined) { cx = view.clientWidth / 2; cy = view.clientHeight / 2; }
    var z0 = ZOOMS[st.zoom], z1 = ZOOMS[k];
    var px = (view.scrollLeft + cx) / z0, py = (view.scrollTop + cy) / z0;
    st.zoom = k;
    layout();
    view.scrollLeft = px * z1 - cx;
    view.scrollTop = py * z1 - cy;
  }

  itemSel.addEventListener("change", function () { setItem(Number(itemSel.value)); });
  layerSel.addEventListener("change", function () { setLayer(Number(layerSel.value)); });
  gainSel.addEventListener("change", function () { st.gain = Number(gainSel.value); show(); });
  hoverBox.addEventListener("change", function () { st.hover = hoverBox.checked; show(); });
  zoomIn.addEventListener("click", function () { zoomTo(st.zoom + 1); });
  zoomOut.addEventListener("click", function () { zoomTo(st.zoom - 1); });
  zoomFit.addEventListener("click", function () { zoomTo(fitZoom()); });

  view.addEventListener("mouseenter", function () { st.inside = true; if (st.hover) { show(); } });
  view.addEventListener("mouseleave", function () {
    st.inside = false; st.drag = null; status.textContent = ""; if (st.hover) { show(); }
  });
  view.addEventListener("wheel", function (ev) {
    ev.preventDefault();
    var r = view.getBoundingClientRect();
    zoomTo(st.zoom + (ev.deltaY < 0 ? 1 : -1), ev.clientX - r.left, ev.clientY - r.top);
  }, {passive: false});
  view.addEventListener("mousedown", function (ev) {
    st.drag = {x: ev.clientX, y: ev.clientY, l: view.scrollLeft, t: view.scrollTop};
    ev.preventDefault();
  });
  window.addEventListener("mouseup", function () { st.drag = null; });
  view.addEventListener("mousemove", function (ev) {
    if (st.drag) {
      view.scrollLeft = st.drag.l - (ev.clientX - st.drag.x);
      view.scrollTop = st.drag.t - (ev.clientY - st.drag.y);
    }
    var r = stack.getBoundingClientRect(), z = ZOOMS[st.zoom];
    var x = Math.floor((ev.clientX - r.left) / z), y = Math.floor((ev.clientY - r.top) / z);
    status.textContent = (x >= 0 && y >= 0 && x < W && y < H) ? "pixel x " + x + ", y " + y : "";
  });

  document.addEventListener("keydown", function (ev) {
    var t = ev.target && ev.target.tagName;
    if (t === "INPUT" || t === "SELECT" || t === "TEXTAREA" || ev.ctrlKey || ev.metaKey || ev.altKey) { return; }
    var k = ev.key, done = true;
    if (k === " " || k === "t" || k === "T") { setMode(st.mode === "a" ? "b" : "a"); }
    else if (k >= "1" && k <= "4") { setMode(MODES[Number(k) - 1][0]); }
    else if (k === "d" || k === "D") { setMode("diff"); }
    else if (k === "e" || k === "E") { setMode("err"); }
    else if (k === "+" || k === "=") { zoomTo(st.zoom + 1); }
    else if (k === "-" || k === "_") { zoomTo(st.zoom - 1); }
    else if (k === "0") { zoomTo(fitZoom()); }
    else if (k === "ArrowRight") { setItem(st.item + 1); }
    else if (k === "ArrowLeft") { setItem(st.item - 1); }
    else if (k === "ArrowDown") { setLayer(st.layer + 1); }
    else if (k === "ArrowUp") { setLayer(st.layer - 1); }
    else { done = false; }
    if (done) { ev.preventDefault(); }
  });

  document.addEventListener("click", function (ev) {   // the technique sections' "compare" links
    var a = ev.target && ev.target.closest && ev.target.closest("[data-cmp-item]");
    if (!a) { return; }
    setItem(Number(a.getAttribute("data-cmp-item")));
    setLayer(Number(a.getAttribute("data-cmp-layer") || 0));
  });

  fillLayers();
  st.zoom = fitZoom();
  show();
  root.setAttribute("data-ready", "1");
})();
"""


def comparator_html(data: dict) -> str:
    """The comparator's HTML: the empty container, its data as JSON and the script.

    ``data`` = {"width": W, "height": H, "items": [:func:`item`, ...]}."""
    text = json.dumps(data, ensure_ascii=False).replace("</", "<\\/")
    return ('<div id="cmp"><noscript>The image comparator needs JavaScript; the images are below.</noscript></div>'
            f'<script type="application/json" id="cmp-data">{text}</script>'
            f"<script>{_JS}</script>")
