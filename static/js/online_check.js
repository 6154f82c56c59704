// The public link's browser check (templates/online_join.html, app.online.pages): finds out what
// the browser can do and posts it; the server decides whether the study can run here. Every
// word the participant reads is in the page, translated; this script only shows and hides them.
(() => {
  const form = document.getElementById("join-form");
  if (!form) return; // a link without the participant's ID: the page says so
  const begin = document.getElementById("check-start");
  let started = false;

  function browserId() {
    // A random id of this browser (not of the person): a second recruitment ID from the same
    // browser is flagged for the researcher, never refused.
    const stored = localStorage.getItem("trustlab.browser");
    if (stored) return stored;
    const bytes = crypto.getRandomValues(new Uint8Array(16));
    const id = btoa(String.fromCharCode(...bytes)).replace(/\+/g, "-").replace(/\//g, "_").replace(/=+$/, "");
    localStorage.setItem("trustlab.browser", id);
    return id;
  }

  function webgl() {
    const canvas = document.createElement("canvas");
    try {
      return Boolean(canvas.getContext("webgl2") || canvas.getContext("webgl"));
    } catch {
      return false;
    }
  }

  async function audio() {
    // Inside the participant's key press or tap, so the browser lets the sound start.
    const Context = window.AudioContext || window.webkitAudioContext;
    if (!Context) return false;
    try {
      const context = new Context();
      const tone = context.createOscillator();
      const volume = context.createGain();
      volume.gain.value = 0.05;
      tone.connect(volume).connect(context.destination);
      tone.start();
      tone.stop(context.currentTime + 0.15);
      await context.resume();
      const running = context.state === "running";
      setTimeout(() => context.close(), 300);
      return running;
    } catch {
      return false;
    }
  }

  async function run({ keyboard, touch }) {
    if (started) return;
    started = true;
    document.getElementById("check-keys").hidden = true;
    document.getElementById("check-running").hidden = false;
    begin.disabled = true;
    const found = {
      webgl: webgl(),
      audio: await audio(),
      width: window.innerWidth,
      height: window.innerHeight,
      keyboard,
      touch,
      browser: browserId(),
    };
    for (const [name, value] of Object.entries(found)) {
      form.elements[name].value = typeof value === "boolean" ? (value ? "1" : "0") : String(value);
    }
    form.submit();
  }

  // The space bar, or Enter on the focused button: either way a keyboard works.
  window.addEventListener("keydown", (event) => {
    const key = event.key.toLowerCase();
    if (key === " " || key === "enter") {
      event.preventDefault();
      run({ keyboard: true, touch: false });
    }
  });
  begin.addEventListener("pointerup", (event) => {
    if (event.pointerType === "touch" || event.pointerType === "pen") run({ keyboard: false, touch: true });
    else document.getElementById("check-keys").hidden = false;
  });
  // Listening now: the invitation to begin shows.
  document.getElementById("check-prompt").hidden = false;
  begin.hidden = false;
})();
