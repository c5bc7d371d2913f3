// Each mode's 3D shape in the report (report_parts.shapes_part): the structure's surface (or its sensors) from
// #shapes3d-data, displaced by the mode's shape through one cycle (Re(shape e^(i phase))), coloured by amplitude
// (grey where the mode is below the noise floor), over its rest position in faint grey. Drawn by plotly.js, inlined
// above: no network. A plot animates only while it is on screen. document.body's data-shapes3d says how many plots
// were drawn, data-shapes3d-errors what failed (the tests read both).
(function () {
  "use strict";
  const errors = [];
  const note = () => {
    document.body.setAttribute("data-shapes3d-errors", errors.join(" | "));
  };
  window.addEventListener("error", (e) => { errors.push(String(e.message)); note(); });
  const data = JSON.parse(document.getElementById("shapes3d-data").textContent);
  const P = data.points_m.map((p) => p.map((x) => 1e3 * x));      // millimetres on the axes
  const col = (k) => P.map((p) => p[k]);
  const X0 = [col(0), col(1), col(2)];
  const span = [0, 1, 2].map((k) => Math.max(...X0[k]) - Math.min(...X0[k]));
  const size = Math.hypot(span[0], span[1], span[2]) || 1;
  const faces = data.faces;
  const corner = (c) => faces.map((f) => f[c]);                   // mesh3d's i, j and k: each face's corners
  const FACE_IJK = { i: corner(0), j: corner(1), k: corner(2) };
  const MOVING = 1;                                                // the displaced trace; 2: its trace lines
  const PERIOD_S = 1.5;                                            // one cycle on screen
  const PLASMA = [[0, "#0d0887"], [0.25, "#7e03a8"], [0.5, "#cc4778"], [0.75, "#f89540"], [1, "#f0f921"]];
  const FRAME_MS = 60;                                             // at most about 16 redraws a second
  const plots = document.querySelectorAll(".shape3d");
  let drawn = 0;

  function lineTrace(x, y, z) {                                    // the sensors' trace lines (no surface)
    const lx = [], ly = [], lz = [];
    for (const [a, b] of data.lines) {
      lx.push(x[a], x[b], null); ly.push(y[a], y[b], null); lz.push(z[a], z[b], null);
    }
    return { type: "scatter3d", mode: "lines", x: lx, y: ly, z: lz, hoverinfo: "skip", showlegend: false,
             line: { color: "#555", width: 3 } };
  }

  function traces(mode, xyz, amp) {
    const colours = mode.judged ? PLASMA : [[0, "#d0d0d0"], [1, "#606060"]];
    const rest = faces.length
      ? { type: "mesh3d", x: X0[0], y: X0[1], z: X0[2], ...FACE_IJK, color: "#bbbbbb", opacity: 0.15,
          hoverinfo: "skip", showscale: false }
      : { type: "scatter3d", mode: "markers", x: X0[0], y: X0[1], z: X0[2], hoverinfo: "skip", showlegend: false,
          marker: { size: 3, color: "#cccccc" } };
    const moving = faces.length
      ? { type: "mesh3d", x: xyz[0], y: xyz[1], z: xyz[2], ...FACE_IJK, intensity: amp, colorscale: colours,
          cmin: 0, cmax: 1, showscale: true,
          colorbar: { title: { text: "amplitude" }, len: 0.6, thickness: 12 }, flatshading: false,
          lighting: { ambient: 0.6, diffuse: 0.6, specular: 0.1 }, hoverinfo: "skip" }
      : { type: "scatter3d", mode: "markers", x: xyz[0], y: xyz[1], z: xyz[2], hoverinfo: "skip", showlegend: false,
          marker: { size: 6, color: amp, colorscale: colours, cmin: 0, cmax: 1, showscale: true } };
    const out = [rest, moving];
    if (!faces.length && data.lines.length) out.push(lineTrace(xyz[0], xyz[1], xyz[2]));
    return out;
  }

  function setup(div) {
    const mode = data.modes[Number(div.dataset.mode)];
    const re = mode.re, im = mode.im;
    const amp = re.map((r, i) => Math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2 + im[i][0] ** 2 + im[i][1] ** 2 +
                                           im[i][2] ** 2));
    const controls = div.parentElement.querySelector(".controls");
    const gain = controls.querySelector(".gain");
    const button = controls.querySelector(".play");
    let playing = true, visible = false, phase = 0, last = null;
    const deform = () => 0.2 * size * Number(gain.value) / 100;   // the largest displacement, mm on screen
    function at(ph) {
      const c = Math.cos(ph), s = Math.sin(ph), k = deform();
      return [0, 1, 2].map((a) => X0[a].map((x, i) => x + k * (re[i][a] * c - im[i][a] * s)));
    }
    const layout = { margin: { l: 0, r: 0, t: 0, b: 0 }, showlegend: false, uirevision: "keep",
                     scene: { aspectmode: "data", xaxis: { title: { text: "x (mm)" } },
                              yaxis: { title: { text: "y (mm)" } }, zaxis: { title: { text: "z (mm)" } },
                              camera: { eye: { x: 1.4, y: 1.4, z: 0.9 } } } };
    return Plotly.newPlot(div, traces(mode, at(0), amp), layout, { displaylogo: false, responsive: true })
      .then(() => {
        drawn += 1;
        div.setAttribute("data-drawn", "1");
        document.body.setAttribute("data-shapes3d", String(drawn));
        function draw() {                                          // the shape at the current phase and gain
          const xyz = at(phase);
          Plotly.restyle(div, { x: [xyz[0]], y: [xyz[1]], z: [xyz[2]] }, [MOVING]);
          if (!faces.length && data.lines.length) {
            const l = lineTrace(xyz[0], xyz[1], xyz[2]);
            Plotly.restyle(div, { x: [l.x], y: [l.y], z: [l.z] }, [MOVING + 1]);
          }
        }
        function frame(t) {
          if (last !== null && t - last < FRAME_MS) {              // a few frames a second: a cycle reads well
            window.requestAnimationFrame(frame);
            return;
          }
          if (playing && visible) {
            if (last !== null) phase = (phase + 2 * Math.PI * (t - last) / 1000 / PERIOD_S) % (2 * Math.PI);
            draw();
          }
          last = playing && visible ? t : null;
          window.requestAnimationFrame(frame);
        }
        window.requestAnimationFrame(frame);
        button.addEventListener("click", () => {
          playing = !playing;
          button.textContent = playing ? "pause" : "play";
        });
        gain.addEventListener("input", () => { if (!playing) draw(); });
        new IntersectionObserver((entries) => { visible = entries[entries.length - 1].isIntersecting; })
          .observe(div);
      });
  }

  Promise.all(Array.from(plots).map((div) => setup(div).catch((e) => { errors.push(String(e)); note(); })))
    .then(() => note());
})();
