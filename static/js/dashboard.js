// The live study dashboard: draws the payloads of dashboard.json with Plotly, and draws them again
// whenever the server says the study changed (server-sent events), at most every 300 ms.
(() => {
  const root = document.getElementById("dashboard");
  if (!root || typeof Plotly === "undefined") return;
  const status = document.getElementById("dashboard-status");
  const charts = document.getElementById("measures");
  const config = { displaylogo: false, responsive: true };
  let latest = null;
  let pending = false;
  // Plotly sizes a plot to its container when it draws it, which may be before the cards beside
  // it exist (the first chart on load), and `responsive` follows only the window: a card that
  // narrows when a measure is toggled would keep a plot wider than itself. Every plot is watched
  // and set to its container's width. (Not Plotly.Plots.resize: it debounces, and a second call
  // within 100 ms drops the first one's promise.) data-resizing counts the resizes in flight.
  let resizing = 0;
  function fit(element) {
    const layout = element._fullLayout;
    if (!layout || Math.abs(layout.width - element.clientWidth) < 1 || !element.clientWidth) return;
    resizing += 1;
    root.dataset.resizing = String(resizing);
    Plotly.relayout(element, { width: element.clientWidth }).finally(() => {
      resizing -= 1;
      root.dataset.resizing = String(resizing);
    });
  }
  const sizes = new ResizeObserver((entries) => entries.forEach((entry) => fit(entry.target)));
  const watch = (element) => sizes.observe(element);
  const plot = (element, payload) =>
    Plotly.react(element, payload.data, payload.layout, config).then(() => fit(element));

  const selected = () =>
    Array.from(root.querySelectorAll('input[name="measure"]:checked')).map((box) => box.value);

  function draw() {
    if (!latest) return;
    const wanted = selected();
    const drawing = [];
    for (const measure of latest.measures) {
      const id = `measure-${measure.item}`;
      let card = document.getElementById(id);
      if (!wanted.includes(measure.item)) {
        if (card) card.remove();
        continue;
      }
      if (!card) {
        card = document.createElement("div");
        card.id = id;
        card.className = "card";
        card.dataset.testid = `measure-${measure.item}`;
        const plot = document.createElement("div");
        plot.className = "chart";
        const empty = document.createElement("p");
        empty.className = "muted small chart-empty";
        empty.textContent = "No answers yet: this fills in as participants complete the " +
          "questionnaire after each session.";
        card.append(plot, empty);
        charts.appendChild(card);
        watch(plot);
      }
      const hasPoints = measure.payload.data.some((trace) => (trace.y || []).length > 0);
      card.querySelector(".chart-empty").hidden = hasPoints;
      drawing.push(plot(card.querySelector(".chart"), measure.payload));
    }
    // null while the study is blinded: the curves would show which group is which
    // (and then the chart's area goes too: an empty 380 px box says nothing)
    const hidden = document.getElementById("adaptation-hidden");
    const adaptation = document.getElementById("adaptation");
    hidden.hidden = latest.adaptation !== null;
    adaptation.hidden = latest.adaptation === null;
    if (latest.adaptation) {
      drawing.push(plot(adaptation, latest.adaptation));
    } else {
      Plotly.purge("adaptation");
      hidden.textContent = `Adaptation curves: ${latest.learners_hidden}.`;
    }
    root.dataset.answers = String(latest.answers);
    root.dataset.questionnaires = String(latest.questionnaires);
    // UTC in 24-hour time, as every other time on the staff pages.
    status.textContent = `${latest.answers} answers learned and ${latest.questionnaires} ` +
      `questionnaire answers so far · updated ${new Date().toISOString().slice(11, 19)} UTC`;
    // data-drawn counts completed draws; the first one is also a performance mark, the moment
    // the dashboard is usable (bench/page_load.py reads it).
    Promise.all(drawing).then(() => {
      const draws = Number(root.dataset.drawn || 0) + 1;
      if (draws === 1) performance.mark("trustlab:dashboard-drawn");
      root.dataset.drawn = String(draws);
    });
  }

  async function refresh() {
    pending = false;
    try {
      const response = await fetch(root.dataset.source, { headers: { Accept: "application/json" } });
      if (!response.ok) throw new Error(`${response.status}`);
      latest = await response.json();
      draw();
    } catch (error) {
      status.textContent = `Could not load the data (${error.message}); retrying.`;
      setTimeout(refresh, 3000);
    }
  }

  watch(document.getElementById("adaptation"));
  root.addEventListener("change", draw);
  const events = new EventSource(root.dataset.events);
  events.addEventListener("changed", () => {
    if (pending) return;
    pending = true;
    setTimeout(refresh, 300);
  });
  refresh();
})();
