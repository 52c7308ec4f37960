"""The verdict page of a report run: ``verdict.md`` and a self-contained ``verdict.html``.

Pure presentation: it takes the claims judged, the compact tables and the scored strips
from :mod:`reports.verdict` (which reads what the report parts wrote into a results folder)
and writes the page and its images into the same folder; it measures nothing and trains
nothing. The page, in order:

1. **Claims.** Each of the paper's claims (:data:`reports.verdict.CLAIMS`) with the paper's figure, ours and a
   verdict, linked to its evidence file. Our numbers come from the run's CSV tables; the
   paper's from :mod:`reports.paper_figures`. A claim measured in both image spaces is judged
   in both, and the verdicts that differ between linear radiance and display-referred
   metrics are listed.
2. **Strips.** Per scene, noisy | ours | mixed | OIDN | reference (those that exist) on one
   view, with an enlarged crop below each and the display PSNR and FLIP of each image under
   the strip. The images are the linear EXRs that the reconstruction part saved beside the
   page (:func:`reports.figures.write_linear_strip`, in ``verdict/SCENE/``; open them in
   tev); they are shown with the metrics' own tonemapping (:mod:`reconstruction.metrics`:
   the exposure that maps the reference's 99th-percentile luminance to white, clipped,
   sRGB), and the crop is :func:`reports.figures.auto_crop` (the window with the most
   reference detail).
3. **Tables.** Compact tables of at most :data:`reports.verdict.MAX_COLUMNS` columns, each header naming
   its unit and image space, each linking its full CSV.
4. **Interactive comparison** (HTML only): per scene, the selected method beside the
   reference on the same view; keys 1-9 or the arrow keys or the tabs switch the method,
   the wheel zooms and dragging pans both images together, a slider changes the exposure in
   stops and re-tonemaps the embedded linear data, and the image's metrics are shown.

**View rule** (:func:`reports.figures.strip_view`): the test view whose reference has the
largest fraction of pixels with luminance at least :data:`reports.figures.LIT_FRACTION` of
display white at the metrics' exposure (ties: the first in name order); a scene no model
saw chooses among all its views. It looks at the references only, so it never picks where
a method looks best, and it avoids mostly black views.

**Linear data in the HTML page.** Each linear image is embedded as an *RGBE-planes PNG*
(:func:`kdtrace.imageio.rgbe_encode`): Radiance's shared-exponent RGBE (8-bit mantissas per channel and
one 8-bit exponent per pixel, relative error at most 1/256 of the pixel's largest channel),
stored as an opaque 8-bit RGB PNG of twice the image's height, the mantissas in the top
half and the exponent in the red channel of the bottom half. Not in an alpha channel: a 2D
canvas stores premultiplied alpha, which would round the mantissas of every pixel whose
exponent is small. The page's script decodes it on a canvas and tonemaps in JavaScript;
nothing is loaded from the network, so the page opens from disk.

Missing inputs are stated on the page, never drawn as broken images; every scene and
plug-in name is HTML-escaped.
"""

from __future__ import annotations

import base64
import html
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kdtrace.cache import atomic_write_bytes
from kdtrace.imageio import png_bytes, rgbe_encode
from kdtrace.markdown import markdown_table
from reports.figures import LIT_FRACTION, STRIP_FOLDER, auto_crop
from reports.verdict import RunTables, Strip, changed_by_space, compact_tables, judge, read_strips, verdict_text

#: File names of the page in a results folder.
VERDICT_MARKDOWN = "verdict.md"
VERDICT_HTML = "verdict.html"
#: Smallest side of one image of a strip PNG, pixels (smaller images are enlarged by whole factors).
STRIP_TILE = 192
#: Gap between the images of a strip PNG, pixels.
STRIP_GAP = 6
#: Colour of the crop outline in the strip (8-bit RGB), as in :mod:`reports.figures`.
CROP_RGB = (255, 212, 0)
#: Displayed width of each canvas of the interactive comparison, CSS pixels.
VIEWER_WIDTH = 420
#: Exposure slider range of the interactive comparison, stops either side of the metrics' exposure.
EXPOSURE_STOPS = 8
#: How the page states the view rule (:func:`reports.figures.strip_view`).
VIEW_RULE_TEXT = ("One view per scene, chosen by the references alone: the test view (a scene no model saw: any view) "
                  "whose reference has the largest fraction of pixels with luminance at least "
                  "{lit:g} of display white at the metrics' exposure; ties go to the first view in name order. Every "
                  "image is shown with the tonemapping of the metrics: exposure mapping the reference's "
                  "99th-percentile luminance to white, clipped, sRGB. The numbers under a strip are of that one view "
                  "(the tables pool all test views). The linear images are the EXR files linked under each strip "
                  "(open them in tev).").format(lit=LIT_FRACTION)


# ------------------------------------------------------------------ strip pictures
def strip_picture(strip: Strip) -> np.ndarray:
    """The strip as one 8-bit RGB picture: every image displayed with the metrics' tonemapping, its crop enlarged below.

    Top row: each shown image (missing ones as a grey tile), enlarged by a whole factor to at
    least :data:`STRIP_TILE` pixels, with the crop (:func:`reports.figures.auto_crop` of the
    reference) outlined; bottom row: the crop of each, enlarged to the same size.
    """
    from reconstruction.metrics import to_display

    reference = strip.reference.image
    height, width = reference.shape[:2]
    factor = max(1, math.ceil(STRIP_TILE / max(height, width)))
    top, left, rows, columns = auto_crop(reference)
    crop_factor = max(1, round(height * factor / rows))
    tiles, crops = [], []
    for item in strip.images:
        if item.image is None:
            shown = np.full((height, width, 3), 0.5)
        else:
            shown = to_display(item.image, strip.exposure)
        encoded = np.round(shown * 255).astype(np.uint8)
        crop = encoded[top:top + rows, left:left + columns]
        crops.append(np.repeat(np.repeat(crop, crop_factor, axis=0), crop_factor, axis=1))
        tile = np.repeat(np.repeat(encoded, factor, axis=0), factor, axis=1)
        y0, x0, y1, x1 = top * factor, left * factor, (top + rows) * factor - 1, (left + columns) * factor - 1
        tile[y0:y1 + 1, [x0, x1]] = CROP_RGB
        tile[[y0, y1], x0:x1 + 1] = CROP_RGB
        tiles.append(tile)
    tile_height, tile_width = tiles[0].shape[:2]
    crop_height, crop_width = crops[0].shape[:2]
    count = len(tiles)
    canvas_width = count * max(tile_width, crop_width) + (count - 1) * STRIP_GAP
    canvas = np.full((tile_height + STRIP_GAP + crop_height, canvas_width, 3), 255, dtype=np.uint8)
    step = max(tile_width, crop_width) + STRIP_GAP
    for index, (tile, crop) in enumerate(zip(tiles, crops, strict=True)):
        canvas[:tile_height, index * step:index * step + tile_width] = tile
        canvas[tile_height + STRIP_GAP:, index * step:index * step + crop_width] = crop
    return canvas


def _metric_cells(strip: Strip) -> tuple[list[str], list[str]]:
    """The display PSNR and FLIP under each image of a strip, as text."""
    psnr_cells, flip_cells = [], []
    for item in strip.images:
        if item is strip.reference:
            psnr_cells.append("(reference)")
            flip_cells.append("(reference)")
        elif item.metrics:
            psnr_cells.append(f"{item.metrics['display_psnr']:.2f}")
            flip_cells.append(f"{item.metrics['flip']:.3f}")
        else:
            psnr_cells.append("—")
            flip_cells.append("—")
    return psnr_cells, flip_cells


# ------------------------------------------------------------------ Markdown
def md_text(text: Any) -> str:
    """Text for a Markdown table cell or line: HTML-escaped (Markdown passes HTML through), ``|`` and brackets escaped."""
    escaped = html.escape(str(text), quote=False)
    return escaped.replace("|", "\\|").replace("[", "\\[").replace("]", "\\]").replace("\n", " ")


def _strip_intro(strip: Strip) -> str:
    exposure = f"exposure {strip.exposure:.4g}" if strip.exposure else "no exposure"
    return (f"View `{md_text(strip.view)}` ({md_text(strip.split)}); {exposure}. "
            "Top: each image with the metrics' tonemapping; below: the outlined crop enlarged.")


def render_markdown(profile: str, findings, changed: list[str], strips: list[Strip], problems: list[str],
                    tables, strip_files: dict[str, str]) -> str:
    """The Markdown page (see the module docstring); ``strip_files``: scene -> strip PNG relative to the page."""
    lines = [f"# Verdict: {md_text(profile)} profile\n",
             "The paper's claims judged on this run, one image strip per scene, compact tables. The interactive "
             f"comparison (switch methods, zoom, exposure) is in [{VERDICT_HTML}]({VERDICT_HTML}); the index of every "
             "file is [README.md](README.md).\n",
             "## 1. The paper's claims\n"]
    rows = []
    for claim, finding in findings:
        verdict = verdict_text(finding)
        rows.append([md_text(claim.text), md_text(claim.paper), md_text(finding.ours if finding else "—"),
                     f"**{md_text(verdict)}** ([{claim.evidence}]({claim.evidence}))"])
    lines.append(markdown_table(["claim (paper)", "paper", "ours", "verdict (evidence)"], rows))
    lines.append("How each verdict is decided (per image space where a claim has both; scenes are the run's):\n")
    lines += [f"{number}. {md_text(claim.rule)}." for number, (claim, _) in enumerate(findings, 1)]
    lines.append("")
    if changed:
        lines.append("**Verdicts that change with the image space** (linear radiance clipped to [0, 1] against "
                     "display-referred: exposed, clipped, sRGB):\n")
        lines += [f"* {md_text(sentence)}" for sentence in changed]
        lines.append("")
    else:
        lines.append("No verdict measured in both image spaces changes between linear radiance and display-referred "
                     "metrics.\n")
    lines.append("## 2. Images\n")
    lines.append(VIEW_RULE_TEXT + "\n")
    lines += [f"> **Missing:** {md_text(problem)}\n" for problem in problems]
    if not strips:
        lines.append(f"> **Missing:** no strip images in `{STRIP_FOLDER}/` (the reconstruction part saves them: "
                     "`kdtrace report --parts reconstruction`).\n")
    for strip in strips:
        lines.append(f"### {md_text(strip.scene)}\n")
        if strip.problem:
            lines.append(f"> **Missing:** {md_text(strip.problem)}; no strip drawn.\n")
            continue
        lines.append(_strip_intro(strip) + "\n")
        lines.append(f"![{md_text(strip.scene)} strip]({strip_files[strip.scene]})\n")
        psnr_cells, flip_cells = _metric_cells(strip)
        lines.append(markdown_table(["", *(md_text(item.label) for item in strip.images)],
                              [["display PSNR (dB, this view)", *psnr_cells], ["FLIP (display, ↓)", *flip_cells],
                               ["linear EXR", *(f"[{item.key}.exr]({item.file})" if item.image is not None else "missing"
                                                for item in strip.images)]]))
        lines += [f"> **Missing:** {md_text(item.label)}: {md_text(item.problem)}\n" for item in strip.images if item.problem]
    lines.append("## 3. Tables\n")
    for spec, rows in tables:
        lines.append(f"### {md_text(spec.title)}\n")
        if rows is None:
            lines.append(f"> **Missing:** `{spec.stem}.csv` is not in this folder or lacks a column of this table.\n")
            continue
        lines.append(markdown_table([md_text(c.header) for c in spec.columns], [[md_text(c) for c in row] for row in rows]))
        lines.append(f"Every column: [{spec.stem}.csv]({spec.stem}.csv), with the notes in [{spec.stem}.md]({spec.stem}.md).\n")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ HTML
def _h(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _html_table(headers: Sequence[str], rows: Sequence[Sequence[str]], extra_row: str = "") -> str:
    """An HTML table of plain-text cells (escaped here), then ``extra_row`` (HTML, already escaped)."""
    head = "".join(f"<th>{_h(cell)}</th>" for cell in headers)
    body = "".join("<tr>" + "".join(f"<td>{_h(cell)}</td>" for cell in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}{extra_row}</tbody></table>"


def _json_for_script(value: Any) -> str:
    """JSON safe inside a ``<script>`` element (``<``, ``>`` and ``&`` as Unicode escapes)."""
    return json.dumps(value).replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def viewer_data(strips: list[Strip]) -> list[dict]:
    """The interactive comparison's data: per drawable strip, its images as base64 RGBE-planes PNGs and their metrics."""
    data = []
    for strip in strips:
        if strip.problem:
            continue
        height, width = strip.reference.image.shape[:2]
        images = []
        for item in strip.images:
            if item.image is None:
                continue
            encoded = base64.b64encode(png_bytes(rgbe_encode(item.image))).decode("ascii")
            images.append({"key": item.key, "label": item.label, "png": f"data:image/png;base64,{encoded}",
                           "psnr": item.metrics.get("display_psnr"), "flip": item.metrics.get("flip"),
                           "reference": item is strip.reference})
        data.append({"scene": strip.scene, "view": strip.view, "width": width, "height": height,
                     "exposure": strip.exposure, "images": images})
    return data


def _viewer_markup(index: int, entry: dict) -> str:
    tabs = "".join(
        f'<button type="button" role="tab" data-index="{i}" aria-selected="{"true" if i == 0 else "false"}">'
        f'<kbd>{i + 1}</kbd> {_h(image["label"])}</button>' for i, image in enumerate(entry["images"]))
    height = round(VIEWER_WIDTH * entry["height"] / entry["width"])
    canvases = "".join(f'<figure><canvas class="{role}" width="{VIEWER_WIDTH}" height="{height}" tabindex="0"></canvas>'
                       f'<figcaption class="{role}-caption"></figcaption></figure>' for role in ("method", "reference"))
    return (f'<section class="viewer" data-index="{index}"><h3>{_h(entry["scene"])} <small>view {_h(entry["view"])}</small></h3>'
            f'<div class="tabs" role="tablist">{tabs}</div><div class="panes">{canvases}</div>'
            f'<div class="controls"><label>exposure <input type="range" class="stops" min="{-EXPOSURE_STOPS}" '
            f'max="{EXPOSURE_STOPS}" step="0.1" value="0"></label> <output class="stops-value">+0.0 stops</output> '
            '<button type="button" class="reset">reset zoom (0)</button></div>'
            '<p class="readout metric"></p><p class="readout pixel"></p></section>')


PAGE_STYLE = """
body{font:15px/1.45 system-ui,sans-serif;margin:1.5em auto;max-width:1400px;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1em}th,td{border:1px solid #ccc;padding:.25em .5em;text-align:left;vertical-align:top}
th{background:#f3f3f3}.verdict{font-weight:600}.missing{background:#fff3cd;border-left:4px solid #e0a800;padding:.4em .8em}
img.strip{max-width:100%;image-rendering:pixelated}.viewer{border:1px solid #ddd;padding:.5em 1em;margin:1em 0}
.viewer.active{border-color:#3573d1}
.tabs button{margin:0 .3em .3em 0;padding:.2em .6em;border:1px solid #999;background:#fff;cursor:pointer}

.tabs button[aria-selected=true]{background:#3573d1;color:#fff;border-color:#3573d1}.panes{display:flex;gap:1em;flex-wrap:wrap}
figure{margin:0}canvas{background:#000;cursor:grab;image-rendering:pixelated;max-width:100%}figcaption{font-size:90%}
.readout{margin:.2em 0;font-size:90%}small{color:#666;font-weight:normal}
"""

#: The interactive comparison (vanilla JavaScript, no library). ``window.kdtraceVerdict`` exposes
#: ``ready``, ``errors`` and the viewers (``select(i)``, ``state()``, ``linear(key)``) for tests.
VIEWER_SCRIPT = r"""
(function () {
  "use strict";
  var api = {ready: false, errors: [], viewers: []};
  window.kdtraceVerdict = api;
  window.addEventListener("error", function (event) { api.errors.push(String(event.message)); });
  var data = JSON.parse(document.getElementById("verdict-data").textContent);
  var active = null;

  function srgb(v) { return v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055; }

  function decode(uri, width, height) {
    // RGBE planes: mantissas in rows [0, H), the exponent in the red channel of rows [H, 2H)
    return new Promise(function (resolve, reject) {
      var picture = new Image();
      picture.onload = function () {
        var canvas = document.createElement("canvas");
        canvas.width = width; canvas.height = 2 * height;
        var context = canvas.getContext("2d", {willReadFrequently: true});
        context.drawImage(picture, 0, 0);
        var bytes = context.getImageData(0, 0, width, 2 * height).data;
        var count = width * height, linear = new Float32Array(3 * count);
        for (var i = 0; i < count; i++) {
          var exponent = bytes[4 * (count + i)];
          if (exponent === 0) { continue; }
          var factor = Math.pow(2, exponent - 136);
          for (var c = 0; c < 3; c++) { linear[3 * i + c] = (bytes[4 * i + c] + 0.5) * factor; }
        }
        resolve(linear);
      };
      picture.onerror = function () { reject(new Error("an embedded image cannot be decoded")); };
      picture.src = uri;
    });
  }

  function Viewer(root, entry) {
    var self = this, width = entry.width, height = entry.height;
    var method = root.querySelector("canvas.method"), reference = root.querySelector("canvas.reference");
    var tabs = Array.prototype.slice.call(root.querySelectorAll(".tabs button"));
    var slider = root.querySelector("input.stops"), stopsText = root.querySelector(".stops-value");
    var metricText = root.querySelector(".metric"), pixelText = root.querySelector(".pixel");
    var referenceIndex = entry.images.findIndex(function (image) { return image.reference; });
    var linear = [], toned = {}, tonedStops = null, selected = 0, zoom = 1, panX = 0, panY = 0, drag = null;
    var base = method.width / width;

    function tone(index) {
      var stops = parseFloat(slider.value);
      if (stops !== tonedStops) { toned = {}; tonedStops = stops; }
      if (toned[index]) { return toned[index]; }
      var scale = entry.exposure * Math.pow(2, stops), values = linear[index];
      var canvas = document.createElement("canvas");
      canvas.width = width; canvas.height = height;
      var context = canvas.getContext("2d"), pixels = context.createImageData(width, height);
      for (var i = 0, n = width * height; i < n; i++) {
        for (var c = 0; c < 3; c++) {
          pixels.data[4 * i + c] = Math.round(255 * srgb(Math.min(1, Math.max(0, values[3 * i + c] * scale))));
        }
        pixels.data[4 * i + 3] = 255;
      }
      context.putImageData(pixels, 0, 0);
      toned[index] = canvas;
      return canvas;
    }

    function paint(canvas, index) {
      var context = canvas.getContext("2d");
      context.setTransform(1, 0, 0, 1, 0, 0);
      context.fillStyle = "#000"; context.fillRect(0, 0, canvas.width, canvas.height);
      context.imageSmoothingEnabled = false;
      context.setTransform(zoom * base, 0, 0, zoom * base, panX, panY);
      context.drawImage(tone(index), 0, 0);
    }

    function describe(image) {
      if (image.reference) { return image.label + " (reference)"; }
      var psnr = image.psnr === null ? "n/a" : image.psnr.toFixed(2) + " dB";
      var flip = image.flip === null ? "n/a" : image.flip.toFixed(3);
      return image.label + ": display PSNR " + psnr + ", FLIP " + flip;
    }

    self.draw = function () {
      paint(method, selected);
      paint(reference, referenceIndex);
      var stops = parseFloat(slider.value);
      stopsText.textContent = (stops >= 0 ? "+" : "") + stops.toFixed(1) + " stops";
      root.querySelector(".method-caption").textContent = entry.images[selected].label;
      root.querySelector(".reference-caption").textContent = entry.images[referenceIndex].label;
      metricText.textContent = describe(entry.images[selected]) + " (this view, at the metrics' exposure " +
        entry.exposure.toPrecision(4) + "; the slider changes the display only)";
    };

    self.select = function (index) {
      selected = (index + entry.images.length) % entry.images.length;
      tabs.forEach(function (tab, i) { tab.setAttribute("aria-selected", i === selected ? "true" : "false"); });
      self.draw();
    };

    self.state = function () {
      return {scene: entry.scene, selected: selected, key: entry.images[selected].key, zoom: zoom, panX: panX,
              panY: panY, stops: parseFloat(slider.value)};
    };
    self.linear = function (key) {
      var index = entry.images.findIndex(function (image) { return image.key === key; });
      return index < 0 ? null : Array.prototype.slice.call(linear[index]);
    };
    self.reset = function () { zoom = 1; panX = 0; panY = 0; self.draw(); };
    self.activate = function () {
      if (active && active !== self) { active.root.classList.remove("active"); }
      active = self; root.classList.add("active");
    };
    self.root = root;

    function canvasPoint(canvas, event) {
      var box = canvas.getBoundingClientRect();
      return [(event.clientX - box.left) * canvas.width / box.width, (event.clientY - box.top) * canvas.height / box.height];
    }

    [method, reference].forEach(function (canvas) {
      canvas.addEventListener("wheel", function (event) {
        event.preventDefault();
        var point = canvasPoint(canvas, event), factor = Math.exp(-event.deltaY * 0.0015);
        var next = Math.min(64, Math.max(0.5, zoom * factor));
        panX = point[0] - (point[0] - panX) * next / zoom;
        panY = point[1] - (point[1] - panY) * next / zoom;
        zoom = next; self.activate(); self.draw();
      }, {passive: false});
      canvas.addEventListener("mousedown", function (event) {
        drag = {x: event.clientX, y: event.clientY, panX: panX, panY: panY, canvas: canvas};
        self.activate(); canvas.focus();
      });
      canvas.addEventListener("mousemove", function (event) {
        var point = canvasPoint(canvas, event);
        var x = Math.floor((point[0] - panX) / (zoom * base)), y = Math.floor((point[1] - panY) / (zoom * base));
        if (x >= 0 && y >= 0 && x < width && y < height) {
          var shown = canvas === method ? selected : referenceIndex, values = linear[shown], i = 3 * (y * width + x);
          pixelText.textContent = "pixel (" + x + ", " + y + ") of " + entry.images[shown].label + ": linear RGB " +
            values[i].toPrecision(4) + ", " + values[i + 1].toPrecision(4) + ", " + values[i + 2].toPrecision(4);
        }
      });
      canvas.addEventListener("dblclick", function () { self.reset(); });
      canvas.addEventListener("focus", function () { self.activate(); });
    });
    window.addEventListener("mousemove", function (event) {
      if (!drag) { return; }
      var box = drag.canvas.getBoundingClientRect(), ratio = drag.canvas.width / box.width;
      panX = drag.panX + (event.clientX - drag.x) * ratio;
      panY = drag.panY + (event.clientY - drag.y) * ratio;
      self.draw();
    });
    window.addEventListener("mouseup", function () { drag = null; });
    tabs.forEach(function (tab, i) {
      tab.addEventListener("click", function () { self.activate(); self.select(i); });
    });
    slider.addEventListener("input", function () { self.activate(); self.draw(); });
    root.querySelector(".reset").addEventListener("click", function () { self.activate(); self.reset(); });
    root.addEventListener("mouseenter", function () { self.activate(); });

    self.load = function () {
      return Promise.all(entry.images.map(function (image) { return decode(image.png, width, height); }))
        .then(function (decoded) { linear = decoded; self.draw(); });
    };
  }

  document.addEventListener("keydown", function (event) {
    if (!active || event.ctrlKey || event.metaKey || event.altKey) { return; }
    if (event.target && event.target.tagName === "INPUT") { return; }
    var state = active.state();
    if (/^[1-9]$/.test(event.key)) { active.select(parseInt(event.key, 10) - 1); }
    else if (event.key === "ArrowRight") { active.select(state.selected + 1); }
    else if (event.key === "ArrowLeft") { active.select(state.selected - 1); }
    else if (event.key === "0") { active.reset(); }
    else { return; }
    event.preventDefault();
  });

  var roots = document.querySelectorAll("section.viewer");
  var loads = [];
  for (var i = 0; i < roots.length; i++) {
    var viewer = new Viewer(roots[i], data[parseInt(roots[i].getAttribute("data-index"), 10)]);
    api.viewers.push(viewer);
    loads.push(viewer.load());
  }
  if (api.viewers.length) { api.viewers[0].activate(); }
  Promise.all(loads).then(function () { api.ready = true; }, function (error) {
    api.errors.push(String(error));
    var note = document.createElement("p");
    note.className = "missing";
    note.textContent = "The interactive comparison could not decode its images: " + error;
    document.getElementById("interactive").appendChild(note);
    api.ready = true;
  });
})();
"""


def render_html(profile: str, findings, changed: list[str], strips: list[Strip], problems: list[str],
                tables, strip_pngs: dict[str, bytes]) -> str:
    """The self-contained HTML page: everything inline (images as data URIs, the viewer's script), nothing fetched."""
    missing = '<p class="missing"><strong>Missing:</strong> {}</p>'.format
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>Verdict: {_h(profile)} profile</title>"
             f"<style>{PAGE_STYLE}</style></head><body><h1>Verdict: {_h(profile)} profile</h1>",
             f'<p>The paper\'s claims judged on this run, one image strip per scene, compact tables, and an interactive '
             f'comparison. Markdown version: <a href="{VERDICT_MARKDOWN}">{VERDICT_MARKDOWN}</a>; every file: '
             '<a href="README.md">README.md</a>.</p>',
             "<h2>1. The paper's claims</h2><table><thead><tr><th>claim (paper)</th><th>paper</th><th>ours</th>"
             "<th>verdict (evidence)</th></tr></thead><tbody>"]
    for claim, finding in findings:
        parts.append(f"<tr><td>{_h(claim.text)}</td><td>{_h(claim.paper)}</td><td>{_h(finding.ours if finding else '—')}</td>"
                     f'<td><span class="verdict">{_h(verdict_text(finding))}</span> '
                     f'(<a href="{_h(claim.evidence)}">{_h(claim.evidence)}</a>)</td></tr>')
    parts.append("</tbody></table><p>How each verdict is decided (per image space where a claim has both; scenes are "
                 "the run's):</p><ol>" + "".join(f"<li>{_h(claim.rule)}.</li>" for claim, _ in findings) + "</ol>")
    if changed:
        parts.append("<p><strong>Verdicts that change with the image space</strong> (linear radiance clipped to [0, 1] "
                     "against display-referred: exposed, clipped, sRGB):</p><ul>"
                     + "".join(f"<li>{_h(sentence)}</li>" for sentence in changed) + "</ul>")
    else:
        parts.append("<p>No verdict measured in both image spaces changes between linear radiance and "
                     "display-referred metrics.</p>")
    parts.append(f"<h2>2. Images</h2><p>{_h(VIEW_RULE_TEXT)}</p>")
    parts += [missing(_h(problem)) for problem in problems]
    if not strips:
        parts.append(missing(f"no strip images in <code>{STRIP_FOLDER}/</code> (the reconstruction part saves them: "
                             "<code>kdtrace report --parts reconstruction</code>)."))
    for strip in strips:
        parts.append(f"<h3>{_h(strip.scene)}</h3>")
        if strip.problem:
            parts.append(missing(_h(strip.problem) + "; no strip drawn."))
            continue
        exposure = f"exposure {strip.exposure:.4g}"
        parts.append(f"<p>View <code>{_h(strip.view)}</code> ({_h(strip.split)}); {exposure}. Top: each image with the "
                     "metrics' tonemapping; below: the outlined crop enlarged.</p>")
        encoded = base64.b64encode(strip_pngs[strip.scene]).decode("ascii")
        parts.append(f'<img class="strip" alt="{_h(strip.scene)} strip" src="data:image/png;base64,{encoded}">')
        psnr_cells, flip_cells = _metric_cells(strip)
        links = "".join(f'<td><a href="{_h(item.file)}">{_h(item.key)}.exr</a></td>' if item.image is not None
                        else "<td>missing</td>" for item in strip.images)
        parts.append(_html_table(["", *(item.label for item in strip.images)],
                                 [["display PSNR (dB, this view)", *psnr_cells], ["FLIP (display, ↓)", *flip_cells]],
                                 f"<tr><td>linear EXR</td>{links}</tr>"))
        parts += [missing(f"{_h(item.label)}: {_h(item.problem)}") for item in strip.images if item.problem]
    parts.append("<h2>3. Tables</h2>")
    for spec, rows in tables:
        parts.append(f"<h3>{_h(spec.title)}</h3>")
        if rows is None:
            parts.append(missing(f"<code>{_h(spec.stem)}.csv</code> is not in this folder or lacks a column of this table."))
            continue
        parts.append(_html_table([c.header for c in spec.columns], rows))
        parts.append(f'<p>Every column: <a href="{_h(spec.stem)}.csv">{_h(spec.stem)}.csv</a>, with the notes in '
                     f'<a href="{_h(spec.stem)}.md">{_h(spec.stem)}.md</a>.</p>')
    data = viewer_data(strips)
    parts.append('<h2 id="interactive">4. Interactive comparison</h2><p>Per scene, the selected method (left) beside the '
                 "reference (right), on the strip's view. Keys <kbd>1</kbd>–<kbd>9</kbd> or <kbd>←</kbd>/<kbd>→</kbd> "
                 "(in the scene under the mouse or last clicked) or the tabs switch the method; the wheel zooms and "
                 "dragging pans both images together; <kbd>0</kbd> or a double click resets; the slider changes the "
                 "exposure in stops from the metrics' exposure and re-tonemaps the embedded linear data (RGBE, "
                 "relative precision 1/256). The metrics are those of the view at the metrics' exposure.</p>")
    if not data:
        parts.append(missing("no linear images to compare in this folder."))
    parts += [_viewer_markup(index, entry) for index, entry in enumerate(data)]
    parts.append(f'<script type="application/json" id="verdict-data">{_json_for_script(data)}</script>')
    parts.append(f"<script>{VIEWER_SCRIPT}</script></body></html>")
    return "".join(parts)


# ------------------------------------------------------------------ the page
def write_page(out_dir: str | Path, profile: str, findings, strips: list[Strip], problems: list[str],
               tables) -> dict[str, Path]:
    """Write ``verdict.md``, ``verdict.html`` and each strip's PNG (``verdict/SCENE/strip.png``) atomically.

    Parameters
    ----------
    out_dir : str or Path
        The results folder.
    profile : str
        Named in the titles.
    findings : list
        :func:`reports.verdict.judge`'s claims and findings.
    strips : list of Strip
        Scored strips (:func:`reports.verdict.read_strips` or :func:`reports.verdict.score_strip`).
    problems : list of str
        Missing-input sentences shown in the images section.
    tables : list
        :func:`reports.verdict.compact_tables`.

    Returns
    -------
    dict
        ``"markdown"``, ``"html"`` -> the pages; ``"strip:SCENE"`` -> each strip PNG.
    """
    out_dir = Path(out_dir)
    changed = changed_by_space(findings)
    written, strip_files, strip_pngs = {}, {}, {}
    for strip in strips:
        if strip.problem:
            continue
        relative = f"{STRIP_FOLDER}/{strip.stem}/strip.png"
        strip_pngs[strip.scene] = png_bytes(strip_picture(strip))
        written[f"strip:{strip.scene}"] = atomic_write_bytes(out_dir / relative, strip_pngs[strip.scene])
        strip_files[strip.scene] = relative
    markdown = render_markdown(profile, findings, changed, strips, problems, tables, strip_files)
    page = render_html(profile, findings, changed, strips, problems, tables, strip_pngs)
    written["markdown"] = atomic_write_bytes(out_dir / VERDICT_MARKDOWN, markdown.encode())
    written["html"] = atomic_write_bytes(out_dir / VERDICT_HTML, page.encode())
    return written


def write_verdict(out_dir: str | Path, profile: str | None = None) -> dict[str, Path]:
    """Write the verdict page of a results folder from what the report parts left there.

    Parameters
    ----------
    out_dir : str or Path
        A results folder (``results/PROFILE``).
    profile : str, optional
        Default: the profile in its ``provenance.json``, else the folder's name.

    Returns
    -------
    dict
        As :func:`write_page`.

    Raises
    ------
    FileNotFoundError
        When ``out_dir`` is not a folder.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"{out_dir}: no such results folder")
    tables = RunTables(out_dir)
    profile = profile or tables.provenance().get("profile") or out_dir.name
    strips, problems = read_strips(out_dir)
    return write_page(out_dir, profile, judge(tables), strips, problems, compact_tables(tables))


def link_from_index(out_dir: str | Path) -> bool:
    """Put the verdict page's line first in an existing index ``README.md`` (after its title); False without an index.

    Idempotent: an index that already links ``verdict.md`` is left as it is.
    """
    index = Path(out_dir) / "README.md"
    if not index.is_file():
        return False
    text = index.read_text()
    if f"]({VERDICT_MARKDOWN})" in text:
        return True
    title, _, rest = text.partition("\n")
    atomic_write_bytes(index, f"{title}\n\n{INDEX_LINE}\n{rest}".encode())
    return True


#: The index's first line after the title (:func:`reports.main.run_report`, :func:`link_from_index`).
INDEX_LINE = (f"**Verdict first:** [{VERDICT_MARKDOWN}]({VERDICT_MARKDOWN}) (the paper's claims, image strips, compact "
              f"tables) and [{VERDICT_HTML}]({VERDICT_HTML}) (the same with an interactive comparison; opens from disk).\n")
