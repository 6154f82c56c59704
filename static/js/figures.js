// Draws the figures whose Plotly payloads the page carries as JSON data blocks
// (<script type="application/json">, which the Content-Security-Policy allows: it never runs),
// on load and in every fragment htmx swaps in later (the mixed-models section).
function drawFigures(root) {
  if (typeof Plotly === "undefined") return;
  for (const target of root.querySelectorAll("[data-figure]")) {
    if (target.dataset.drawn) continue;
    const source = document.getElementById(target.dataset.figure);
    if (!source) continue;
    const payload = JSON.parse(source.textContent);
    target.dataset.drawn = "1";
    Plotly.newPlot(target, payload.data, payload.layout, { displaylogo: false, responsive: true });
  }
}

document.addEventListener("DOMContentLoaded", () => drawFigures(document));
document.addEventListener("htmx:load", (event) => drawFigures(event.detail.elt));
