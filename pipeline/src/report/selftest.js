// Self-test of the page, run only when the URL has ?selftest=1 or #selftest (the browser
// test opens it so in headless Chromium and reads the JSON written into the pre element
// of id "selftest").
// Not part of the page's behaviour: it records errors, then on load exercises the page's
// own sorting and filtering code as a reader would (clicks, typing) and reports what it saw,
// with the widths of the page and of the table's scrolling box.
(function () {
  "use strict";
  if (!/[?&]selftest=1\b/.test(location.search) && location.hash !== "#selftest") { return; }
  var errors = [];
  window.addEventListener("error", function (e) { errors.push("error: " + e.message); });
  window.addEventListener("securitypolicyviolation", function (e) { errors.push("csp: " + e.violatedDirective + " " + e.blockedURI); });
  var consoleError = console.error;
  console.error = function () { errors.push("console.error: " + Array.prototype.join.call(arguments, " ")); consoleError.apply(console, arguments); };
  function visible() {
    var rows = document.getElementById("targets").tBodies[0].rows;
    return Array.prototype.filter.call(rows, function (r) { return !r.hidden; })
      .map(function (r) { return r.getAttribute("data-target") + "/" + r.getAttribute("data-comp"); });
  }
  function header(k) { return document.querySelector('#targets th[data-key="' + k + '"] button'); }
  window.addEventListener("load", function () {
    var out = { errors: errors };
    try {
      out.images = Array.prototype.map.call(document.images, function (im) {
        return { alt: im.alt, complete: im.complete, naturalWidth: im.naturalWidth };
      });
      var box = document.getElementById("targets").parentNode;
      out.layout = { inner_width: window.innerWidth, page_width: document.documentElement.scrollWidth,
        table_box: box.clientWidth, table_width: box.scrollWidth };
      out.initial = visible();
      header("snr").click();
      out.sort_snr_first = visible();
      out.sort_snr_first_dir = header("snr").parentNode.getAttribute("aria-sort");
      header("snr").click();
      out.sort_snr_second = visible();
      var hide = document.getElementById("hide-failed");
      hide.click();
      out.hide_failed = visible();
      hide.click();
      var m = /[?&]q=([^&]*)/.exec(location.search);
      var text = document.getElementById("filter");
      text.value = m ? decodeURIComponent(m[1]) : "";
      text.dispatchEvent(new Event("input"));
      out.text_filter = { q: text.value, rows: visible() };
      text.value = "";
      text.dispatchEvent(new Event("input"));
      out.after_clear = visible();
    } catch (e) {
      errors.push("selftest: " + e);
    }
    var pre = document.getElementById("selftest");
    pre.textContent = JSON.stringify(out);
  });
})();
