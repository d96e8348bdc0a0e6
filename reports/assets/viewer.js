/* mpe3d's offline point-cloud viewer: ground truth against a reconstruction,
 * turned with the mouse (drag), a finger (swipe) or the keyboard (arrows);
 * the wheel zooms. No library and no network: the clouds are embedded in the
 * page as <script type="application/json" id="..."> blocks, and each
 * <canvas class="mpe3d-cloud" data-cloud="ID"> draws the one it names. */
(function () {
  "use strict";
  var TRUTH = "rgba(107, 174, 214, 0.55)", OURS = "rgb(178, 24, 43)";

  function rotate(p, yaw, pitch) {
    var cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
    var x = cy * p[0] + sy * p[2], z = -sy * p[0] + cy * p[2];
    return [x, cp * p[1] - sp * z, sp * p[1] + cp * z];
  }

  function view(canvas) {
    var data = JSON.parse(document.getElementById(canvas.dataset.cloud).textContent);
    var all = data.truth.concat(data.ours), centre = [0, 0, 0], radius = 1e-12;
    all.forEach(function (p) { for (var i = 0; i < 3; i++) centre[i] += p[i] / all.length; });
    all.forEach(function (p) {
      radius = Math.max(radius, Math.hypot(p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]));
    });
    var state = {yaw: 0.6, pitch: 0.35, zoom: 1, drag: null};
    var ctx = canvas.getContext("2d");

    function dots(points, colour, size) {
      var scale = state.zoom * 0.45 * Math.min(canvas.width, canvas.height) / radius;
      var placed = points.map(function (p) {
        return rotate([p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]], state.yaw, state.pitch);
      });
      placed.sort(function (a, b) { return a[2] - b[2]; });  // far first
      ctx.fillStyle = colour;
      placed.forEach(function (q) {
        ctx.beginPath();
        ctx.arc(canvas.width / 2 + scale * q[0], canvas.height / 2 - scale * q[1], size, 0, 2 * Math.PI);
        ctx.fill();
      });
    }

    function draw() {
      ctx.fillStyle = "#fff";
      ctx.fillRect(0, 0, canvas.width, canvas.height);
      dots(data.truth, TRUTH, 3.2);  // wide pale discs under small dark dots: both stay visible
      dots(data.ours, OURS, 1.3);
      ctx.font = "11px sans-serif";
      [[TRUTH, "ground truth"], [OURS, "reconstruction (aligned)"]].forEach(function (item, i) {
        ctx.fillStyle = item[0];
        ctx.beginPath();
        ctx.arc(12, 14 + 16 * i, 4, 0, 2 * Math.PI);
        ctx.fill();
        ctx.fillStyle = "#222";
        ctx.fillText(item[1], 22, 18 + 16 * i);
      });
      canvas.dataset.rendered = String(Number(canvas.dataset.rendered || 0) + 1);
    }

    function turn(dx, dy) {
      state.yaw += dx * 0.01;
      state.pitch = Math.max(-1.55, Math.min(1.55, state.pitch + dy * 0.01));
      draw();
    }

    canvas.addEventListener("pointerdown", function (e) {
      state.drag = [e.clientX, e.clientY];
      if (canvas.setPointerCapture) canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointermove", function (e) {
      if (!state.drag) return;
      turn(e.clientX - state.drag[0], e.clientY - state.drag[1]);
      state.drag = [e.clientX, e.clientY];
    });
    ["pointerup", "pointercancel", "pointerleave"].forEach(function (name) {
      canvas.addEventListener(name, function () { state.drag = null; });
    });
    canvas.addEventListener("wheel", function (e) {
      e.preventDefault();
      state.zoom = Math.max(0.2, Math.min(8, state.zoom * (e.deltaY < 0 ? 1.1 : 1 / 1.1)));
      draw();
    }, {passive: false});
    canvas.tabIndex = 0;
    canvas.addEventListener("keydown", function (e) {
      var step = {ArrowLeft: [-10, 0], ArrowRight: [10, 0], ArrowUp: [0, -10], ArrowDown: [0, 10]}[e.key];
      if (step) { e.preventDefault(); turn(step[0], step[1]); }
    });
    draw();
  }

  function start() {
    Array.prototype.forEach.call(document.querySelectorAll("canvas.mpe3d-cloud"), view);
  }
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
  else start();
})();
