// The participant's tablet: keep answers typed but not yet sent across reloads and crashes, and
// move on by itself when the server has a new page (a session ended, a participant was seated).
(() => {
  const SUBMITTED = "trustlab:submitted";
  const form = document.querySelector("form[data-draft-key]");
  const draftKey = form ? "trustlab:draft:" + form.dataset.draftKey : null;

  const timingOf = (key) => key.replace("trustlab:draft:", "trustlab:timing:");

  // A draft whose page was submitted is no longer needed once we are on another page.
  const submitted = sessionStorage.getItem(SUBMITTED);
  if (submitted && submitted !== draftKey) {
    localStorage.removeItem(submitted);
    localStorage.removeItem(timingOf(submitted));
    sessionStorage.removeItem(SUBMITTED);
  }

  if (form) {
    // How long this page is open and, of that, how long its tab is hidden (data quality:
    // app/services/participants/data_quality.py). Kept with the draft, so a reload or a return
    // after closing the tab goes on counting from the first time the page was shown.
    const timingKey = timingOf(draftKey);
    const timing = JSON.parse(localStorage.getItem(timingKey) || "null") || { opened: Date.now(), away: 0 };
    const keepTiming = () => localStorage.setItem(timingKey, JSON.stringify(timing));
    keepTiming();
    let hiddenSince = document.hidden ? Date.now() : null;
    const hiddenUntilNow = () => (hiddenSince === null ? 0 : Math.max(0, Date.now() - hiddenSince));
    document.addEventListener("visibilitychange", () => {
      if (document.hidden) {
        hiddenSince = Date.now();
      } else {
        timing.away += hiddenUntilNow();
        hiddenSince = null;
        keepTiming();
      }
    });
    form.addEventListener("submit", () => {
      const open = Math.max(0, Date.now() - timing.opened);
      form.elements["page-seconds"].value = (open / 1000).toFixed(3);
      form.elements["away-seconds"].value = ((timing.away + hiddenUntilNow()) / 1000).toFixed(3);
    });

    const fields = () => Array.from(form.elements).filter((el) => el.name && el.type !== "hidden");
    const saved = JSON.parse(localStorage.getItem(draftKey) || "null");
    if (saved) {
      for (const el of fields()) {
        if (!(el.name in saved)) continue;
        if (el.type === "radio" || el.type === "checkbox") {
          if (!form.querySelector(`[name="${el.name}"]:checked`)) el.checked = saved[el.name] === el.value;
        } else if (!el.value) {
          el.value = saved[el.name];
        }
      }
    }
    const save = () => {
      const draft = {};
      for (const el of fields()) {
        if ((el.type === "radio" || el.type === "checkbox") && !el.checked) continue;
        if (el.value !== "") draft[el.name] = el.value;
      }
      localStorage.setItem(draftKey, JSON.stringify(draft));
    };
    form.addEventListener("input", save);
    form.addEventListener("change", save);
    form.addEventListener("submit", () => sessionStorage.setItem(SUBMITTED, draftKey));

    // After a refused submit the server marks what is missing: take the participant to the first
    // such item (its first control, so a screen reader reads the question and its message).
    const firstMissing = form.querySelector(".item.invalid");
    if (firstMissing) {
      const control = firstMissing.querySelector("input, textarea, select");
      firstMissing.scrollIntoView({ block: "center" });
      if (control) control.focus({ preventScroll: true });
    }
  }

  const stream = document.body.dataset.events;
  if (stream) {
    // Participant changes the page acts on by name (app/services/participants/participant_changes.py): an
    // erasure ends the tablet's link, so the tablet says its thanks on a page that needs none,
    // in the language it shows; an anonymisation ends it too, and the page shown stays right.
    const ERASED = "participant_erased";
    const ANONYMISED = "participant_anonymised";
    // On a page with a form, only a change of the participant (or of the consent text) reloads
    // it: typed answers are kept as drafts, but a reload on every event of a kiosk's station
    // would take the participant's place in the page away. Other events move it only when the
    // server would now show another page.
    const onForm = Boolean(document.querySelector("main form"));
    const source = new EventSource(stream);
    let leaving = false;
    let timer = null;
    const stop = () => {
      leaving = true;
      source.close();
      clearInterval(timer);
    };
    const go = (path) => {
      if (leaving) return;
      stop();
      window.location.replace(path);
    };
    // Where the server would send this tablet now: go there if it moved on.
    const followIfMoved = async () => {
      try {
        const now = await fetch("/tablet", { credentials: "same-origin" });
        if (new URL(now.url).pathname !== window.location.pathname) go("/tablet");
      } catch (error) {
        // the next event, or the interval below, looks again
      }
    };
    source.addEventListener("changed", (event) => {
      let types = [];
      try {
        types = JSON.parse(event.data).types || [];
      } catch (error) {
        // an event without its types: treated as any change
      }
      if (types.includes(ERASED)) go("/tablet/left");
      else if (types.includes(ANONYMISED)) stop();
      else if (!onForm || types.some((type) => type.startsWith("participant_") || type === "consent_changed")) go("/tablet");
      else followIfMoved();
    });
    // A change that happened before the stream was listening sends no event: once it is
    // listening, ask where the server would send this tablet now, and go there if it moved on.
    source.addEventListener("open", () => {
      document.body.dataset.listening = "yes"; // for people and tests: changes will reach it
      followIfMoved();
    });
    // Belt and braces: look again once a minute even if the event stream is down.
    timer = setInterval(() => (onForm ? followIfMoved() : go("/tablet")), 60000);
  }
})();
