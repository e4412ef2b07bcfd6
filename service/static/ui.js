// autocal monitoring page: show or hide the per-band series of the history plots.
"use strict";
document.addEventListener("DOMContentLoaded", function () {
  var box = document.getElementById("show-bands");
  if (!box) { return; }
  var apply = function () { document.body.classList.toggle("hide-bands", !box.checked); };
  box.addEventListener("change", apply);
  apply();
});
