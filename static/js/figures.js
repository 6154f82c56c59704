// Draws the figures whose Plotly payloads the page carries as JSON data blocks
// (<script type="application/json">, which the Content-Security-Policy allows: it never runs).
document.addEventListener("DOMContentLoaded", () => {
  if (typeof Plotly === "undefined") return;
  for (const target of document.querySelectorAll("[data-figure]")) {
    const source = document.getElementById(target.dataset.figure);
    if (!source) continue;
    const payload = JSON.parse(source.textContent);
    Plotly.newPlot(target, payload.data, payload.layout, { displaylogo: false, responsive: true });
  }
});
