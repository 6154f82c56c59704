// The room's words in the seated participant's language.
//
// Sentences are written in English in the room's scripts and page, marked with _() (the page's
// static ones carry data-t, the English message id). When the station's state names another
// language, its catalogue comes from /api/v1/languages/<code>/words (the same gettext catalogue
// the tablet uses, app/i18n/locales) and every marked sentence on the page is said again in it.

let table = {};
let current = "en";

/** ``message`` (an English message id) in the current language, ``%(name)s`` filled in. */
export function _(message, values = {}) {
  const text = table[message] || message;
  return text.replace(/%\((\w+)\)[sd]/g, (whole, name) => (name in values ? String(values[name]) : whole));
}

/** The current language's code ("en" until a participant in another language is seated). */
export function language() {
  return current;
}

/** Switch to ``code`` (a no-op when it is current); resolves once the page speaks it. A
 * language without a catalogue keeps the page in English and says so on the console. */
export async function useLanguage(code) {
  if (!code || code === current) return;
  let words = { language: "en", direction: "ltr", messages: {} };
  if (code !== "en") {
    const response = await fetch(`/api/v1/languages/${encodeURIComponent(code)}/words`);
    if (!response.ok) {
      console.warn(`no interface words for ${code}: the room stays in English`);
      return;
    }
    words = await response.json();
  }
  table = words.messages;
  current = code;
  document.documentElement.lang = code;
  document.documentElement.dir = words.direction;
  for (const node of document.querySelectorAll("[data-t]")) node.textContent = _(node.dataset.t);
  for (const node of document.querySelectorAll("[data-t-label]")) {
    node.setAttribute("aria-label", _(node.dataset.tLabel));
  }
}
