// The robot's voice and the participant's: speech synthesis for the robot's lines (the browser's
// voices, else the trustlab server's), and the browser's own speech recognition for yes/no
// answers, used only where the protocol allows a cloud recogniser ([speech] cloud_recognizer;
// otherwise microphone.js streams to the server's offline recogniser). Captions are always shown
// as well (room.js), so a browser without either still runs the whole study.
//
// A recognised answer counts only when it is a clear yes or a clear no: "yes", "yeah, sure" or
// "no, not really" are; "yes… no", "I don't know", "maybe" and anything heard with low confidence
// are not, and the robot asks again. Real participants hesitate and correct themselves, and a
// misheard answer would teach the learner the wrong thing. The protocol's own phrases for the
// participant's language ([speech] yes/no and their translations: "ja", "nej tack") count as
// well; the built-in English words and hedges only where the participant speaks English.

export const MIN_CONFIDENCE = 0.5;

const YES = new Set([
  "yes", "yeah", "yea", "yep", "yup", "ya", "yah", "aye", "sure", "certainly", "definitely",
  "absolutely", "correct", "affirmative", "indeed", "right",
]);
const NO = new Set(["no", "nope", "nah", "negative", "never", "not", "incorrect", "wrong"]);
const UNSURE = [
  /\b(don'?t|do not|dunno) know\b/, /\bnot sure\b/, /\bmaybe\b/, /\bperhaps\b/, /\bi guess\b/,
  /\bkind of\b/, /\bsort of\b/, /\bwhat\b/, /\bpardon\b/, /\brepeat\b/,
];

/** Lower case, letters of any script (with their combining marks: the vowel signs of Indic
 * scripts, Thai tone marks) and apostrophes only, single spaces. */
function normalise(text) {
  return String(text || "")
    .normalize("NFC")
    .toLowerCase()
    .replace(/[’`]/g, "'")
    .replace(/[^\p{L}\p{M}' ]+/gu, " ")
    .replace(/\s+/g, " ")
    .trim();
}

/** Whether ``text`` (normalised) says one of ``phrases`` as whole words. */
function says(text, phrases) {
  return (phrases || []).some((phrase) => {
    const words = normalise(phrase);
    return words !== "" && ` ${text} `.includes(` ${words} `);
  });
}

/** "yes", "no" or null (not a clear answer) for what a recogniser heard. ``phrases``: the
 * protocol's ``yes`` and ``no`` phrases in the participant's language, and whether that language
 * is English (the built-in words and hedges are English). */
export function classifyAnswer(transcript, phrases = { yes: [], no: [], english: true }) {
  const text = normalise(transcript);
  const english = phrases.english !== false;
  if (!text || (english && UNSURE.some((pattern) => pattern.test(text)))) return null;
  const words = text.split(" ");
  const saidYes =
    says(text, phrases.yes) ||
    (english && (words.some((word) => YES.has(word)) || /\bof course\b/.test(text)));
  const saidNo =
    says(text, phrases.no) ||
    (english && words.some((word) => NO.has(word) || word === "don't" || word === "didn't"));
  if (saidYes === saidNo) return null; // neither, or both ("yes no", "right, no", "ja nej")
  return saidYes ? "yes" : "no";
}

/** What the recogniser's best guess (its first alternative) says: a clear answer heard with
 * enough confidence, with its words and confidence, or ``{answer: null, …}`` with the same words
 * when it is not. The other alternatives are not consulted: a guess the recogniser ranked lower
 * is no evidence of what the participant said. */
export function pickAnswer(alternatives, minConfidence = MIN_CONFIDENCE, phrases = undefined) {
  const heard = alternatives
    .filter((alternative) => alternative && alternative.transcript)
    .map((alternative) => ({
      transcript: String(alternative.transcript).trim().slice(0, 200),
      confidence: Number.isFinite(alternative.confidence) ? alternative.confidence : 0,
    }));
  if (heard.length === 0) return { answer: null, transcript: "", confidence: 0 };
  const top = heard[0];
  const answer = classifyAnswer(top.transcript, phrases);
  if (answer === null || top.confidence < minConfidence) return { answer: null, ...top };
  return { answer, ...top };
}

/** The robot's voice: speaks a line and resolves when it has been said (or when it would have
 * been, where nothing can speak it or the end is never reported). The browser's own voices speak
 * where it has any; otherwise the trustlab server's synthesised audio of the line plays
 * (``serverLine(text)`` resolves with its WAV as an ArrayBuffer, or null: then captions only). */
export class Voice {
  constructor(enabled = true, serverLine = null) {
    this.enabled = enabled;
    this.synth = enabled && "speechSynthesis" in window ? window.speechSynthesis : null;
    this.serverLine = enabled ? serverLine : null;
    this.decoded = new Map(); // text → AudioBuffer: each line is fetched and decoded once
    this.context = null;
    this.playing = null;
    this.serverSilent = false; // the server cannot synthesise (503): captions only from then on
    if (this.synth && typeof this.synth.getVoices === "function") this.synth.getVoices(); // Chrome loads them lazily
  }

  /** Whether the browser has voices of its own (headless and minimal installs have none). */
  get browserVoices() {
    if (!this.synth) return false;
    if (typeof this.synth.getVoices !== "function") return true;
    return this.synth.getVoices().length > 0;
  }

  say(text) {
    this.stop();
    if (this.browserVoices) return this._sayInBrowser(text);
    if (this.serverLine && !this.serverSilent) return this._sayFromServer(text);
    return this._pause(text);
  }

  _pause(text) {
    const estimate = 600 + text.length * 70;
    return new Promise((resolve) => setTimeout(resolve, Math.min(estimate, 1500)));
  }

  _sayInBrowser(text) {
    const estimate = 600 + text.length * 70;
    return new Promise((resolve) => {
      let done = false;
      const finish = () => {
        if (!done) {
          done = true;
          resolve();
        }
      };
      const utterance = new SpeechSynthesisUtterance(text);
      utterance.lang = document.documentElement.lang || "en";
      utterance.onend = finish;
      utterance.onerror = finish;
      setTimeout(finish, estimate + 2000);
      this.synth.speak(utterance);
    });
  }

  async _sayFromServer(text) {
    let buffer = this.decoded.get(text);
    try {
      if (!this.context) this.context = new AudioContext();
      if (this.context.state === "suspended") await this.context.resume().catch(() => {});
      if (!buffer) {
        const wav = await this.serverLine(text);
        if (wav === "unavailable") this.serverSilent = true;
        if (!(wav instanceof ArrayBuffer)) return this._pause(text);
        buffer = await this.context.decodeAudioData(wav);
        this.decoded.set(text, buffer);
      }
    } catch {
      return this._pause(text);
    }
    return new Promise((resolve) => {
      const source = this.context.createBufferSource();
      source.buffer = buffer;
      source.connect(this.context.destination);
      const finish = () => {
        if (this.playing && this.playing.source === source) this.playing = null;
        resolve();
      };
      source.onended = finish;
      this.playing = { source, finish };
      // a context that never plays (no output device, a policy) must not hold the room up
      setTimeout(finish, buffer.duration * 1000 + 2000);
      source.start();
    });
  }

  stop() {
    if (this.synth) this.synth.cancel();
    if (this.playing) {
      const { source, finish } = this.playing;
      this.playing = null;
      try {
        source.stop();
      } catch {
        // never started
      }
      finish();
    }
  }
}

/** Listens for one yes/no answer at a time (where the browser offers speech recognition), in
 * the participant's language, for the protocol's phrases of it (``phrases``: as
 * :func:`classifyAnswer` takes them). */
export class Listener {
  constructor(enabled = true, phrases = undefined) {
    const Recognition = enabled && (window.SpeechRecognition || window.webkitSpeechRecognition);
    this.Recognition = Recognition || null;
    this.phrases = phrases;
    this.active = null;
  }

  get available() {
    return this.Recognition !== null;
  }

  /** Resolves with ``pickAnswer``'s result for what was heard, or null when nothing was (silence,
   * no microphone, a refused permission, or :meth:`stop`). */
  listen() {
    if (!this.available) return Promise.resolve(null);
    this.stop();
    return new Promise((resolve) => {
      const recognition = new this.Recognition();
      recognition.lang = document.documentElement.lang || "en";
      recognition.interimResults = false;
      recognition.maxAlternatives = 3;
      let settled = false;
      const settle = (value) => {
        if (!settled) {
          settled = true;
          this.active = null;
          resolve(value);
        }
      };
      recognition.onresult = (event) => {
        const result = event.results[event.results.length - 1];
        settle(pickAnswer(Array.from(result), MIN_CONFIDENCE, this.phrases));
      };
      recognition.onerror = () => settle(null);
      recognition.onend = () => settle(null);
      this.active = { recognition, settle };
      try {
        recognition.start();
      } catch {
        settle(null);
      }
    });
  }

  stop() {
    if (this.active) {
      const { recognition, settle } = this.active;
      settle(null);
      try {
        recognition.abort();
      } catch {
        // already stopped
      }
    }
  }
}
