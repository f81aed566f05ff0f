// Sorting (click a column header; numeric columns sort by their data-v number, missing
// values last) and filtering ("hide failed targets", a text filter) of the targets table.
(function () {
  "use strict";
  var table = document.getElementById("targets");
  if (!table) { return; }
  var tbody = table.tBodies[0];
  var heads = table.tHead.rows[0].cells;
  function key(row, col, numeric) {
    var td = row.cells[col];
    if (!td) { return null; }
    if (numeric) {
      var x = parseFloat(td.getAttribute("data-v"));
      return isNaN(x) ? null : x;
    }
    return td.textContent.trim().toLowerCase();
  }
  function sortBy(th) {
    var col = th.cellIndex;
    var numeric = th.getAttribute("data-type") === "num";
    var dir = th.getAttribute("aria-sort") === "ascending" ? -1 : 1;
    for (var i = 0; i < heads.length; i++) { heads[i].removeAttribute("aria-sort"); }
    th.setAttribute("aria-sort", dir === 1 ? "ascending" : "descending");
    var rows = Array.prototype.slice.call(tbody.rows);
    rows.sort(function (a, b) {
      var x = key(a, col, numeric), y = key(b, col, numeric);
      if (x === null || y === null) { return x === y ? 0 : (x === null ? 1 : -1); }
      return x < y ? -dir : (x > y ? dir : 0);
    });
    rows.forEach(function (r) { tbody.appendChild(r); });
  }
  Array.prototype.forEach.call(heads, function (th) {
    var b = th.querySelector("button");
    if (b) { b.addEventListener("click", function () { sortBy(th); }); }
  });
  var hide = document.getElementById("hide-failed");
  var text = document.getElementById("filter");
  var shown = document.getElementById("shown");
  function apply() {
    var q = text.value.trim().toLowerCase();
    var n = 0;
    Array.prototype.forEach.call(tbody.rows, function (r) {
      var off = (hide.checked && r.getAttribute("data-status") === "failed") ||
        (q !== "" && r.textContent.toLowerCase().indexOf(q) < 0);
      r.hidden = off;
      if (!off) { n++; }
    });
    shown.textContent = n + " of " + tbody.rows.length + " rows shown";
  }
  hide.addEventListener("change", apply);
  text.addEventListener("input", apply);
  apply();
})();
