// Refusals on every staff page, one mechanism: when an htmx request fails, the server's own words
// appear next to the control that sent it, and a region that can reload itself does, so the page
// shows the state the refusal is about. htmx never swaps a 4xx/5xx answer, so without this a
// refused request would change nothing on screen.
(() => {
  const HEADER = "X-Trustlab-Refusal";
  const UNREACHABLE =
    "The server could not be reached: nothing was changed. Check the connection and try again.";
  let pending = null; // {action, region, message, typed}: shown again after the region reloads

  function messageOf(xhr) {
    const header = xhr.getResponseHeader(HEADER);
    if (header) return decodeURIComponent(header);
    try {
      const detail = JSON.parse(xhr.responseText).detail;
      if (typeof detail === "string" && detail) return detail;
    } catch (_) {
      // not JSON: fall through to the status
    }
    if (xhr.status >= 500) {
      // A server fault can come after the change was stored: do not claim it was not.
      return `The server failed (HTTP ${xhr.status}); reload the page to see whether the change was made.`;
    }
    return `The server refused the request (HTTP ${xhr.status}); nothing was changed.`;
  }

  function anchorOf(elt) {
    return (elt && elt.closest("form")) || elt;
  }

  function show(anchor, message) {
    if (!anchor || !anchor.isConnected) return;
    let note = anchor.nextElementSibling;
    if (!(note && note.classList.contains("refusal"))) {
      note = document.createElement("p");
      note.className = "error refusal";
      note.setAttribute("role", "alert");
      anchor.after(note);
    }
    note.textContent = message;
  }

  // What the person typed into the refused form, so a reloaded region gives it back.
  function typedValues(form) {
    if (!form || form.tagName !== "FORM") return [];
    return Array.from(form.elements)
      .filter((field) => field.name && field.type !== "hidden" && field.type !== "submit")
      .map((field) => [field.name, field.value]);
  }

  function restore(form, typed) {
    for (const [name, value] of typed) {
      const field = form.elements.namedItem(name);
      if (field && "value" in field) field.value = value;
    }
  }

  function clear() {
    pending = null;
    document.querySelectorAll("p.refusal").forEach((note) => note.remove());
  }

  function refuse(elt, message) {
    // An earlier request's outcome (p.notice: "Enrolled P1: allocated to …") would read as this
    // request's, beside the refusal that says otherwise.
    document.querySelectorAll("p.notice").forEach((notice) => notice.remove());
    const anchor = anchorOf(elt);
    const region = elt && elt.closest("[data-refresh-on-refusal]");
    pending = {
      action: anchor && anchor.getAttribute("action"),
      region: region && region.id,
      message,
      typed: typedValues(anchor),
    };
    show(anchor, message);
    if (region) htmx.trigger(region, "trustlab:refresh");
  }

  document.addEventListener("htmx:beforeRequest", (event) => {
    // A person's new request replaces the old refusal; a region reloading itself does not.
    if (anchorOf(event.detail.elt) && event.detail.elt.closest("form")) clear();
  });
  document.addEventListener("htmx:responseError", (event) => {
    refuse(event.detail.elt, messageOf(event.detail.xhr));
  });
  document.addEventListener("htmx:sendError", (event) => refuse(event.detail.elt, UNREACHABLE));
  document.addEventListener("htmx:timeout", (event) => refuse(event.detail.elt, UNREACHABLE));
  document.addEventListener("htmx:afterSettle", () => {
    if (!pending) return;
    const { action, region, message, typed } = pending;
    if (document.querySelector("p.refusal")) return; // still on screen
    const form = action && document.querySelector(`form[action="${CSS.escape(action)}"]`);
    if (form) {
      restore(form, typed);
      return show(form, message);
    }
    // The control is gone (the state moved on): say it at the top of its region.
    const home = region && document.getElementById(region);
    if (home) {
      const note = document.createElement("p");
      note.className = "error refusal";
      note.setAttribute("role", "alert");
      note.textContent = message;
      home.prepend(note);
    }
  });
})();
