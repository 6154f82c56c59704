// Draws the figures whose Plotly payloads the page carries as data: a JSON data block named by
// data-figure (<script type="application/json">, which the Content-Security-Policy allows: it
// never runs) or, in fragments htmx swaps in (htmx drops their script elements), the element's
// own data-figure-payload attribute. On load, and in every fragment swapped in later.
function drawFigures(root) {
  if (typeof Plotly === "undefined") return;
  for (const target of root.querySelectorAll("[data-figure], [data-figure-payload]")) {
    if (target.dataset.drawn) continue;
    let text = target.dataset.figurePayload;
    if (text === undefined) {
      const source = document.getElementById(target.dataset.figure);
      if (!source) continue;
      text = source.textContent;
    }
    const payload = JSON.parse(text);
    target.dataset.drawn = "1";
    Plotly.newPlot(target, payload.data, payload.layout, { displaylogo: false, responsive: true });
  }
}

document.addEventListener("DOMContentLoaded", () => drawFigures(document));
document.addEventListener("htmx:load", (event) => drawFigures(event.detail.elt));
