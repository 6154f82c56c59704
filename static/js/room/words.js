// The room's words in the seated participant's language.
//
// Sentences are written in English in the room's scripts and page, marked with _() (the page's
// static ones carry data-t, the English message id). When the station's state names another
// language, its catalogue comes from /api/v1/languages/<code>/words (the same gettext catalogue
// the tablet uses, app/i18n/locales) and every marked sentence on the page is said again in it.
// A sentence the scripts put on the page goes through show(), which marks it the same way, so a
// badge or caption drawn before the words arrived is redrawn when they do (never left in English).
// The operator's own screens (the device-key form) are English on purpose and say so with
// staff() (tests/app/test_languages.py fails on any other literal sentence in these scripts).

let table = {};
let current = "en";
const missing = new Set();

/** ``message`` (an English message id) in the current language, ``%(name)s`` filled in. */
export function _(message, values = {}) {
  const text = table[message] || message;
  return text.replace(/%\((\w+)\)[sd]/g, (whole, name) => (name in values ? String(values[name]) : whole));
}

/** Put ``message`` (an English message id, ``values`` filled in) in ``node`` in the current
 * language, marked so that every later language switch says it again in the new one. */
export function show(node, message, values = null) {
  node.dataset.t = message;
  if (values) node.dataset.tValues = JSON.stringify(values);
  else delete node.dataset.tValues;
  node.textContent = _(message, values || {});
}

/** A sentence for the lab's staff, not the participant: English on purpose (the device-key form
 * and the room's messages about keys and browsers, docs/languages.md "Not translated yet"). */
export function staff(text) {
  return text;
}

/** The key a participant presses for ``answer`` ("yes" or "no"), as the catalogue names it:
 * Y and N in English, J and N in Swedish and German. */
export function answerKey(answer) {
  return answer === "yes" ? _("Y") : _("N");
}

/** The current language's code ("en" until a participant in another language is seated). */
export function language() {
  return current;
}

/** Whether ``code``'s words are unavailable (no catalogue: the room stays in English). */
export function unavailable(code) {
  return missing.has(code);
}

/** Switch to ``code`` (a no-op when it is current); resolves once the page speaks it. A
 * language without a catalogue keeps the page in English and says so on the console. */
export async function useLanguage(code) {
  if (!code || code === current || missing.has(code)) return;
  let words = { language: "en", direction: "ltr", messages: {} };
  if (code !== "en") {
    let response = null;
    try {
      response = await fetch(`/api/v1/languages/${encodeURIComponent(code)}/words`);
    } catch {
      return; // the network: asked again with the next state
    }
    if (!response.ok) {
      missing.add(code);
      console.warn(`no interface words for ${code}: the room stays in English`);
      return;
    }
    words = await response.json();
  }
  table = words.messages;
  current = code;
  document.documentElement.lang = code;
  document.documentElement.dir = words.direction;
  redraw();
}

/** Say every marked sentence of the page again in the current language. */
function redraw() {
  for (const node of document.querySelectorAll("[data-t]")) {
    node.textContent = _(node.dataset.t, node.dataset.tValues ? JSON.parse(node.dataset.tValues) : {});
  }
  for (const node of document.querySelectorAll("[data-t-label]")) {
    node.setAttribute("aria-label", _(node.dataset.tLabel));
  }
  for (const node of document.querySelectorAll("[data-t-keys]")) {
    node.setAttribute("aria-keyshortcuts", _(node.dataset.tKeys));
  }
}
