// The layout probe of tests/report_browser.rs (tests/report_browser/layout.rs): inserted by
// the test into a copy of the night's page (never part of the page sofipol writes), it
// measures on load what a reader sees at the window's width and reports it as JSON, written
// into <pre id="layout-probe"> and, when the page is inside the test's iframe (the 390 px
// phone), posted to the parent page too.
// - page: the viewport's width and the document's (wider: the page scrolls sideways);
// - boxes: per table inside a horizontally scrolling box, the box's width and its content's;
// - clipped: cells (and elements inside them) whose content is cut off: wider than their own
//   box, or reaching past an ancestor that hides overflow (not one that scrolls), or past the
//   viewport;
// - figures: per image, the section it is in, the link around it, its width and the width of
//   the main column;
// - sequences: the lines the standards' sequence ids are laid out on.
(function () {
  "use strict";
  function label(el) {
    var t = el.closest("table");
    var row = el.closest("tr");
    var text = (el.textContent || "").trim().replace(/\s+/g, " ").slice(0, 60);
    return (t && t.id ? "#" + t.id : "table") + " row " + (row ? row.rowIndex : "?") + ": " + text;
  }
  function scrollsX(el) {
    var o = getComputedStyle(el).overflowX;
    return o === "auto" || o === "scroll";
  }
  function hidesX(el) {
    var o = getComputedStyle(el).overflowX;
    return o === "hidden" || o === "clip";
  }
  function clippedCells() {
    var out = [];
    var viewport = document.documentElement.clientWidth;
    var all = document.querySelectorAll("td, th, td *, th *");
    Array.prototype.forEach.call(all, function (el) {
      var cell = el.matches("td, th");
      // A cell's content wider than the cell overlaps or is cut; inside a cell, an element
      // cuts its content only when it hides its overflow (text-overflow needs that too).
      if ((cell || hidesX(el)) && el.scrollWidth > el.clientWidth + 1 && !scrollsX(el)) {
        out.push("content wider than its box (" + el.scrollWidth + " > " + el.clientWidth + " px): " + label(el));
        return;
      }
      if (!cell) { return; }
      var r = el.getBoundingClientRect();
      for (var a = el.parentElement; a; a = a.parentElement) {
        if (scrollsX(a)) { return; }
        if (hidesX(a)) {
          var b = a.getBoundingClientRect();
          if (r.right > b.right + 1 || r.left < b.left - 1) {
            out.push("cut off by an ancestor hiding overflow: " + label(el));
          }
          return;
        }
      }
      if (r.right > viewport + 1) {
        out.push("past the viewport (" + Math.round(r.right) + " > " + viewport + " px): " + label(el));
      }
    });
    return out;
  }
  function boxes() {
    return Array.prototype.map.call(document.querySelectorAll("table"), function (t) {
      var a = t.parentElement;
      while (a && !scrollsX(a)) { a = a.parentElement; }
      return { table: t.id, box: a ? a.clientWidth : null, content: a ? a.scrollWidth : null };
    });
  }
  function figures() {
    var main = document.querySelector("main") || document.body;
    var cs = getComputedStyle(main);
    var column = main.clientWidth - parseFloat(cs.paddingLeft) - parseFloat(cs.paddingRight);
    return Array.prototype.map.call(document.images, function (im) {
      var a = im.closest("a[href]");
      var s = im.closest("section");
      return { section: s ? s.id : "", alt: im.alt, href: a ? a.href : null,
        width: Math.round(im.getBoundingClientRect().width), natural_width: im.naturalWidth,
        column: Math.round(column) };
    });
  }
  // The text of each line an element's text is laid out on (a character per range).
  function lines(el) {
    var out = [];
    var top = null;
    var walk = document.createTreeWalker(el, NodeFilter.SHOW_TEXT);
    for (var n = walk.nextNode(); n; n = walk.nextNode()) {
      for (var i = 0; i < n.data.length; i++) {
        var r = document.createRange();
        r.setStart(n, i);
        r.setEnd(n, i + 1);
        var rects = r.getClientRects();
        if (!rects.length) { continue; }
        var t = rects[0].top;
        if (top === null || Math.abs(t - top) > 2) { out.push(""); top = t; }
        out[out.length - 1] += n.data[i];
      }
    }
    return out.map(function (s) { return s.trim(); });
  }
  function sequences() {
    var cells = document.querySelectorAll("#standards tbody td:first-child .muted");
    return Array.prototype.map.call(cells, function (s) {
      return { text: s.textContent, lines: lines(s) };
    });
  }
  window.addEventListener("load", function () {
    var out = {};
    try {
      out = { inner_width: window.innerWidth, page_width: document.documentElement.scrollWidth,
        boxes: boxes(), clipped: clippedCells(), figures: figures(), sequences: sequences() };
    } catch (e) {
      out = { error: "probe: " + e };
    }
    var json = JSON.stringify(out);
    var pre = document.createElement("pre");
    pre.id = "layout-probe";
    pre.hidden = true;
    pre.textContent = json;
    document.body.appendChild(pre);
    if (window.parent !== window) { window.parent.postMessage(json, "*"); }
  });
})();
