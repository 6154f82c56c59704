// Live regions on staff pages: a region the page's event stream keeps current never misses the
// last change of a burst. A region says which stream event refreshes it and how often at most:
// data-live="EVENT MS" beside hx-trigger="sse:EVENT throttle:MSms, trustlab:refresh".
//
// htmx alone can leave a region stale until the next change: its throttle drops an event that
// comes within MS of the last refresh, and a refresh queued behind one in flight is dropped
// when that one's swap replaces the region (outerHTML). So every event is counted here, each
// refresh notes the count when it starts, and when a refresh ends (or a dropped event leaves
// none on its way) with events it did not see, one more refresh follows, MS after the last.
//
// A region that a refresh swapped in (outerHTML) is processed by htmx only when it settles, a
// settle delay after the swap (later still on a busy machine). Until then it hears neither a
// trigger, so the catch-up waits for its htmx:load, nor the stream: the htmx SSE extension
// hands the next event to the region it replaced, now detached, which counts it here.
(() => {
  const regions = new Map(); // id -> {seen, covered, inFlight (requests on their way), started, timer}

  function stateOf(id) {
    if (!regions.has(id)) {
      regions.set(id, { seen: 0, covered: 0, inFlight: 0, started: 0, timer: null });
    }
    return regions.get(id);
  }

  function settingsOf(region) {
    const [event, gap] = (region.dataset.live || "").split(" ");
    return { event, gap: Number(gap) || 0 };
  }

  /** Refresh the region once more if an event came after its last refresh started. */
  function catchUp(id) {
    const state = stateOf(id);
    const region = document.getElementById(id);
    if (!region || state.covered >= state.seen || state.inFlight || state.timer) return;
    const wait = Math.max(0, state.started + settingsOf(region).gap - Date.now());
    state.timer = setTimeout(() => {
      state.timer = null;
      const current = document.getElementById(id);
      // Not yet settled after a swap, it would not hear this: its htmx:load catches up again.
      if (current && state.covered < state.seen && !state.inFlight) {
        htmx.trigger(current, "trustlab:refresh");
      }
    }, wait);
  }

  function heard(id) {
    stateOf(id).seen += 1;
    setTimeout(() => catchUp(id), 0); // after htmx has decided
  }

  function watch(eventName) {
    // Capture: counted before htmx's own listener on the region starts (or drops) a refresh.
    document.addEventListener(
      `sse:${eventName}`,
      (event) => {
        const region = event.target;
        if (!(region instanceof Element) || !region.id || !region.dataset.live) return;
        if (settingsOf(region).event !== eventName) return;
        heard(region.id);
      },
      true,
    );
  }

  /** Count an event the stream hands to ``region`` once a swap has detached it (the document
   * does not hear it): its replacement is not listening yet. */
  const detachedWatched = new WeakSet();
  function watchDetached(region) {
    const { event } = settingsOf(region);
    if (!event || !region.id || detachedWatched.has(region)) return;
    detachedWatched.add(region);
    region.addEventListener(`sse:${event}`, () => {
      if (!region.isConnected) heard(region.id);
    });
  }

  document.addEventListener("htmx:beforeRequest", (event) => {
    const region = event.detail.elt;
    if (!(region instanceof Element) || !region.id || !region.dataset.live) return;
    const state = stateOf(region.id);
    state.inFlight += 1; // a count: htmx may start a queued refresh before this one's loadend
    state.started = Date.now();
    state.covered = state.seen;
    event.detail.xhr.addEventListener("loadend", () => {
      state.inFlight -= 1; // after htmx's swap: the region shows what this refresh read
      catchUp(region.id);
    });
  });

  // What someone is typing in a live region outlives the region's refresh: the swapped-in
  // copy gets back each edited field's text (and the focus, if it was there), matched by its
  // form's action and its name. A form's own submission swaps without this: its answer is new.
  const typed = new Map(); // region id -> {values: Map(key -> value), focused: key}
  const TYPED = "input[name]:not([type=hidden]):not([type=checkbox]):not([type=radio]), textarea[name]";

  function fieldKey(field) {
    return `${field.form ? field.form.getAttribute("action") : ""}|${field.name}`;
  }

  document.addEventListener("htmx:beforeSwap", (event) => {
    const region = event.detail.requestConfig && event.detail.requestConfig.elt;
    if (!(region instanceof Element) || !region.id || !region.dataset.live) return;
    const values = new Map();
    let focused = null;
    region.querySelectorAll(TYPED).forEach((field) => {
      if (field.value === field.defaultValue) return;
      values.set(fieldKey(field), field.value);
      if (field === document.activeElement) focused = fieldKey(field);
    });
    if (values.size) typed.set(region.id, { values, focused });
  });

  document.addEventListener("htmx:afterSwap", () => {
    typed.forEach(({ values, focused }, id) => {
      typed.delete(id);
      const region = document.getElementById(id);
      if (!region) return;
      region.querySelectorAll(TYPED).forEach((field) => {
        const key = fieldKey(field);
        if (!values.has(key) || field.value !== field.defaultValue) return;
        field.value = values.get(key);
        if (key === focused) field.focus({ preventScroll: true });
      });
    });
  });

  function liveRegionsIn(root) {
    const regionsIn = [...root.querySelectorAll("[data-live]")];
    if (root.matches && root.matches("[data-live]")) regionsIn.push(root); // a swapped-in region
    return regionsIn;
  }

  const watched = new Set();
  function watchRegions(root) {
    liveRegionsIn(root).forEach((region) => {
      const { event } = settingsOf(region);
      if (event && !watched.has(event)) {
        watched.add(event);
        watch(event);
      }
      watchDetached(region);
    });
  }
  document.addEventListener("DOMContentLoaded", () => watchRegions(document));
  document.addEventListener("htmx:afterSettle", (event) => watchRegions(event.target));
  // Swapped-in content is processed: a catch-up that found it deaf can go now.
  document.addEventListener("htmx:load", (event) => {
    if (!(event.target instanceof Element)) return;
    liveRegionsIn(event.target).forEach((region) => region.id && catchUp(region.id));
  });
})();
