// The escape room client: a participant walks the maze, trigger zones ask the robot's questions,
// the robot speaks and replies, and the answers go to trustlab through the public robot API only
// (the station WebSocket and GET /api/v1/station/room), as any third-party client's would.
//
// One way data flows: the server's station state (from hello, pushes and replies) decides what
// may happen; the walk decides only where the participant is. A reload, a crash or a dropped
// network resumes from the server's state: the open question is shown again, an answer that was
// sent but not acknowledged is sent again with the same idempotency key, and the participant's
// place in the current run is kept in this tab.

import { RoomScene, webglAvailable } from "./room/scene.js";
import { ServerListener } from "./room/microphone.js";
import { StationSocket } from "./room/socket.js";
import { Listener, Voice } from "./room/speech.js";
import { _, answerKey, language, show, staff, unavailable, useLanguage } from "./room/words.js";
import {
  inside,
  normaliseHeading,
  poseFromHeadset,
  startPose,
  step,
  wallSegments,
  zoneAt,
} from "./room/walk.js";

const root = document.getElementById("room");
const station = root.dataset.station;
// Where the station API is: the robot API's, or a study's preview (app.web.preview_room), which
// answers the same requests for signed-in staff, from memory, and needs no device key.
const API = root.dataset.api || "/api/v1/station";
const PREVIEW = root.dataset.preview === "true";
// An online participant's own room (app.online.pages): its key comes with the page, the
// participant starts each session, and the room hands over to their next page when its part ends.
const ONLINE = Boolean(root.dataset.start);
const stores = {
  key: `trustlab.room.key.${station}`,
  answer: `trustlab.room.answer.${station}`,
  pose: `trustlab.room.pose.${station}`,
  exited: `trustlab.room.exited.${station}`,
};
const PRESENCE_INTERVAL_MS = 500; // the console's room panel: at most two reports a second
const PRESENCE_KEEPALIVE_MS = 10000; // and at least one every ten seconds
const DRAG_DEGREES = 0.25; // a mouse drag turns the participant this much per pixel
const RETRY_REFUSED_MS = 3000; // a refused prompt is not asked again sooner (standing in its zone)
const ASK_AGAIN = () => _("Sorry, I did not catch that. Please answer yes or no."); // until [speech] is read
const TO_THE_EXIT = () => _("Now walk to the exit: the solid circle.");
const el = (id) => document.getElementById(id);
const options = new URLSearchParams(location.search);

// ?listen=off: no voice answers. Off too with ?voice=off (unless ?listen=on): the recogniser
// would hear the robot reading its own question ("…are you sure?") as the participant's answer.
const LISTEN = (options.get("listen") ?? (options.get("voice") === "off" ? "off" : "on")) !== "off";
const NOT_LISTENING = { available: false, listen: async () => null, stop() {} };

const room = {
  key: PREVIEW ? "preview" : root.dataset.key || localStorage.getItem(stores.key) || "",
  socket: null,
  layout: null,
  segments: [],
  scene: null,
  state: null, // the station's state as the server last said it
  pose: null,
  question: null, // the open prompt shown to the participant
  shown: null, // the step id of the last question shown here (its reply may come from elsewhere)
  answeredHere: new Set(), // step ids answered from this tab (their replies come as results)
  promptInFlight: null, // the category whose prompt was requested and not yet answered
  refused: new Map(), // category → when the server last refused its prompt
  answering: false,
  resumed: false,
  held: new Set(),
  dragged: 0,
  exitHint: false,
  frames: 0,
  presence: { at: 0, x: NaN, z: NaN, heading: NaN, zone: undefined, said: null },
  voice: new Voice(options.get("voice") !== "off", serverLine), // ?voice=off: a physical robot speaks
  listener: NOT_LISTENING, // the server's recogniser, or the browser's where the protocol allows it
  speech: null, // the study's [speech] settings (GET /api/v1/station/speech)
  study: null, // the study whose room is drawn
  loading: false,
  everOnline: false,
  lastReport: 0,
  said: null, // the last caption said ({kind, text}): the browser tests' view of it
  speaking: null, // the robot's line being said (a promise, settled when it has been said)
  saying: false, // whether that line is still being said
  switching: null, // the language switch under way, and the newest state waiting for it
  waiting: null,
};

// ---------------------------------------------------------------- what the server says

function runKey(state = room.state) {
  if (!state || !state.participant || !state.session || !state.run) return "";
  return `${state.participant}/${state.session.number}/${state.run.number}`;
}

function sessionKey(state) {
  if (!state || !state.participant) return "";
  return `${state.participant}/${state.session ? state.session.number : ""}`;
}

function sessionRunning() {
  return Boolean(room.state && room.state.session && room.state.session.status === "running");
}

/** The run is answered in full, another run of the session comes next, and the participant has
 * not walked out through the exit yet. After a session's last run there is no walk out: the
 * server expects the tablet (or the next session), and the room says so at once. */
function needsExit() {
  const state = room.state;
  return Boolean(
    sessionRunning() && state.run && state.run.status === "completed" &&
      sessionStorage.getItem(stores.exited) !== runKey(),
  );
}

function canWalk() {
  return Boolean(room.layout) && sessionRunning();
}

/** Make the room what the server's state says, whatever led here: the room's own request, a
 * push about something done elsewhere (Wizard-of-Oz, the console), a reload or a reconnection.
 * A state in another language waits for that language's words: nothing of it (a caption, the
 * way out, a banner) is drawn in the previous language first. */
function applyState(state) {
  if (state.language && state.language !== language() && !unavailable(state.language)) {
    room.waiting = state; // the newest state is drawn once the words are here
    if (!room.switching) {
      room.switching = switchLanguage(state.language).finally(() => {
        const waiting = room.waiting;
        room.switching = null;
        room.waiting = null;
        if (waiting) drawState(waiting); // (a network failure: drawn as it is, asked again next time)
      });
    }
    return;
  }
  drawState(state);
}

function drawState(state) {
  const before = room.state;
  room.state = state;
  if (state.study && room.study && state.study !== room.study) closeRoom(); // another study's room
  if (!room.scene && state.study && !room.loading) loadRoom(); // e.g. a seating we did not hear of
  if ((before && before.participant) !== state.participant) newParticipant();
  else if (sessionKey(before) !== sessionKey(state)) hideCaption(); // the last session's words
  if (runKey(before) !== runKey(state)) {
    room.refused.clear();
    restorePose();
  }
  if (state.run && state.run.status === "ended_early" && sessionStorage.getItem(stores.exited) !== runKey()) {
    sessionStorage.setItem(stores.exited, runKey()); // the experimenter ended it: back to the start
    room.pose = room.layout ? startPose(room.layout) : null;
  }
  if (!sessionRunning() && room.layout) {
    room.pose = startPose(room.layout); // out of the room until the next session starts
    room.held.clear();
  }
  const open = state.open_prompts || [];
  if (!room.question && open.length > 0 && !room.promptInFlight) {
    showQuestion(open[0], { speak: true });
  } else if (room.question && !room.answering && !open.some((p) => p.step_id === room.question.step_id)) {
    // Answered elsewhere (its reply is in the state: see answeredElsewhere), or its run ended.
    closeQuestion();
    if (el("captions").dataset.kind === "question") hideCaption();
  }
  answeredElsewhere(state.last_reply);
  if (needsExit() && !room.answering) guideToExit();
  render();
}

/** Another participant is seated (or nobody is): nothing of the last one's stays on screen or
 * goes to the console as theirs, and the console hears at once where this one stands. */
function newParticipant() {
  hideCaption();
  room.presence = { ...room.presence, at: 0, x: NaN, said: null };
  room.shown = null;
}

/** The reply to the shown question when someone else answered it (Wizard-of-Oz on the console):
 * the participant hears it as if the room had sent the answer. It comes in the state (its
 * last_reply), so whether the answer_recorded push brought it or a reconnection after the room
 * was cut off, the reply is said once. */
function answeredElsewhere(last) {
  const step = last && last.step_id;
  if (!step || step !== room.shown || room.answeredHere.has(step) || !last.reply) return;
  room.shown = null;
  say("reply", last.reply, { speak: true, hint: needsExit() ? TO_THE_EXIT() : "" });
}

/** Between two runs the participant walks out through the exit; the caption says so whenever
 * it does not already (after a reply elsewhere, a reload or a reconnection too). */
function guideToExit() {
  if (!el("captions").hidden && el("caption-text").textContent.includes(TO_THE_EXIT())) return;
  say("robot", TO_THE_EXIT(), { speak: false });
}

async function refreshState() {
  try {
    applyState(await room.socket.request("state"));
  } catch {
    // the next push or hello brings it
  }
}

// ---------------------------------------------------------------- walking

function restorePose() {
  if (!room.layout) return;
  const saved = JSON.parse(sessionStorage.getItem(stores.pose) || "null");
  const here = runKey();
  if (saved && here && saved.run === here && Number.isFinite(saved.x)) {
    room.pose = { x: saved.x, z: saved.z, heading: saved.heading };
  } else if (!room.pose || !here || (saved && saved.run && saved.run.split("/")[0] !== here.split("/")[0])) {
    room.pose = startPose(room.layout); // a new participant, or no run yet
  }
}

function savePose() {
  const { x, z, heading } = room.pose;
  sessionStorage.setItem(stores.pose, JSON.stringify({ run: runKey(), x, z, heading }));
}

function input() {
  const held = room.held;
  const axis = (plus, minus) => (plus ? 1 : 0) - (minus ? 1 : 0);
  return {
    forward: axis(held.has("forward"), held.has("back")),
    turn: axis(held.has("turn-right"), held.has("turn-left")),
    strafe: axis(held.has("strafe-right"), held.has("strafe-left")),
  };
}

function frame(seconds) {
  room.frames += 1;
  if (!room.pose) return;
  if (room.scene.renderer.xr.isPresenting) {
    const view = room.scene.headsetView();
    room.pose = poseFromHeadset(room.layout, view.position, view.direction);
  } else if (canWalk()) {
    room.pose = step(room.layout, room.segments, room.pose, input(), seconds);
    if (room.dragged) room.pose.heading = normaliseHeading(room.pose.heading + room.dragged);
  }
  room.dragged = 0;
  room.scene.update(room.pose);
  afterMove();
}

function afterMove() {
  const { x, z } = room.pose;
  const zone = zoneAt(room.layout, x, z);
  if (inside(room.layout.exit, x, z)) reachExit();
  else room.exitHint = false;
  if (zone) maybePrompt(zone);
  reportPresence(zone);
}

function reachExit() {
  if (needsExit()) {
    sessionStorage.setItem(stores.exited, runKey());
    room.pose = startPose(room.layout);
    room.held.clear(); // a key still held from the walk out does not walk them off again
    say("robot", _("Well done! Back to the start for the next run."), { speak: true });
    render();
  } else if (sessionRunning() && !room.exitHint && room.state.run && room.state.run.status === "running") {
    room.exitHint = true;
    say("robot", _("Not yet: there is more to find in the room before the exit."), { speak: false });
  }
}

function maybePrompt(zone) {
  const state = room.state;
  if (needsExit()) guideToExit(); // a zone asks nothing before the walk out: say where to go
  if (!state || !room.socket || room.question || room.promptInFlight || needsExit()) return;
  const expected = state.expected;
  if (expected.action !== "prompt" || !expected.categories.includes(zone.category)) return;
  if (performance.now() - (room.refused.get(zone.category) ?? -Infinity) < RETRY_REFUSED_MS) return;
  room.promptInFlight = zone.category;
  performance.mark(`trustlab:zone:${zone.category}`);
  room.socket
    .request("prompt", { category: zone.category, zone: zone.category })
    .then((prompt) => {
      room.promptInFlight = null;
      if (!room.question) showQuestion(prompt, { speak: true, zone: zone.category });
      refreshState();
    })
    .catch((error) => {
      room.promptInFlight = null;
      room.refused.set(zone.category, performance.now()); // e.g. the run was ended meanwhile
      showDetail(serverWords(error.detail));
      refreshState();
    });
}

// ---------------------------------------------------------------- asking and answering

function showQuestion(prompt, { speak, zone } = {}) {
  room.question = prompt;
  room.shown = prompt.step_id;
  say("question", prompt.question, { speak: false });
  if (zone) {
    requestAnimationFrame(() => {
      // the frame that draws the caption: what bench/room.py reports as zone → caption
      performance.mark("trustlab:caption");
      performance.measure("trustlab:zone-to-caption", `trustlab:zone:${zone}`, "trustlab:caption");
    });
  }
  el("answer").hidden = false;
  render();
  if (speak) askAloud(prompt.question);
}

function closeQuestion() {
  room.question = null;
  room.answering = false;
  room.listener.stop();
  el("answer").hidden = true;
  el("listening").hidden = true;
}

async function askAloud(text) {
  const asked = room.question;
  await room.voice.say(text);
  let silences = 0;
  while (room.question === asked && !room.answering && room.listener.available && silences < 3) {
    const listener = room.listener;
    el("listening").hidden = false;
    const heard = await listener.listen(asked.step_id, { seconds: speechSettings().listen_seconds });
    el("listening").hidden = true;
    if (room.question !== asked || room.answering) return;
    if (heard === null) {
      silences += 1; // silence, no microphone, or a refused permission: the buttons remain
      continue;
    }
    silences = 0;
    if (heard.transcript) say("participant", heard.transcript, { speak: false });
    if (heard.recorded) {
      replied(heard.recorded); // the server heard a clear answer and recorded it
      return;
    }
    if (heard.answer) {
      answer(heard.answer, "speech", heard);
      return;
    }
    const again = speechSettings().reprompt;
    say("robot", again, { speak: false });
    await room.voice.say(again);
  }
}

function randomKey() {
  const bytes = new Uint8Array(16);
  crypto.getRandomValues(bytes); // works without HTTPS, unlike crypto.randomUUID
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

function answer(value, modality, heard) {
  if (!room.question || room.answering) return;
  room.answering = true;
  room.answeredHere.add(room.question.step_id);
  room.listener.stop();
  room.voice.stop();
  const pending = {
    step_id: room.question.step_id,
    answer: value,
    idempotency_key: randomKey(),
    modality,
  };
  if (modality === "speech" && heard) {
    pending.transcript = heard.transcript;
    pending.transcript_confidence = Math.max(0, Math.min(1, heard.confidence));
    pending.transcript_engine = heard.engine || "browser";
  }
  localStorage.setItem(stores.answer, JSON.stringify(pending)); // before sending: a crash resends it
  if (modality !== "speech") say("participant", value === "yes" ? _("Yes.") : _("No."), { speak: false });
  sendAnswer(pending);
}

function sendAnswer(pending) {
  el("answer").hidden = true;
  room.socket
    .request("answer", pending)
    .then((reply) => {
      localStorage.removeItem(stores.answer);
      replied(reply);
    })
    .catch((error) => {
      localStorage.removeItem(stores.answer);
      room.answering = false;
      if (error.status === 409 || error.status === 404) {
        closeQuestion(); // the run ended before the answer arrived: nothing to record
        showDetail(serverWords(error.detail));
      } else {
        el("answer").hidden = false;
        showDetail(_("The answer was not taken. Please answer again."));
      }
      refreshState();
    });
}

/** The robot's reply to an answer given here (sent by the room, or recognised and recorded by
 * the server from the room's audio). */
function replied(reply) {
  room.answeredHere.add(reply.step_id); // its answer_recorded push is not replied to again
  closeQuestion();
  const hint = reply.run_completed && !reply.session_completed ? TO_THE_EXIT() : "";
  say("reply", reply.reply, { speak: true, hint });
  refreshState();
}

function resumeStoredAnswer() {
  const stored = JSON.parse(localStorage.getItem(stores.answer) || "null");
  if (!stored) return;
  room.answering = true;
  room.answeredHere.add(stored.step_id);
  if (!room.question) room.question = { step_id: stored.step_id, question: "" };
  sendAnswer(stored);
}

// ---------------------------------------------------------------- presence and captions

function say(kind, text, { speak, hint } = {}) {
  el("captions").hidden = false;
  if (kind === "participant") show(el("caption-speaker"), "You:");
  else show(el("caption-speaker"), "Robot:");
  el("caption-text").textContent = hint ? `${text} ${hint}` : text;
  el("captions").dataset.kind = kind;
  room.presence.said = { kind, text: text.slice(0, 300) };
  room.said = { kind, text };
  if (!speak) return;
  const line = room.voice.say(text);
  room.speaking = line;
  room.saying = true;
  line.then(() => {
    if (room.speaking === line) room.saying = false;
  });
}

function hideCaption() {
  el("captions").hidden = true;
  delete el("captions").dataset.kind;
}

function reportPresence(zone) {
  if (!room.socket || !room.socket.online) return;
  const now = performance.now();
  const last = room.presence;
  if (now - last.at < PRESENCE_INTERVAL_MS) return;
  const { x, z, heading } = room.pose;
  const category = zone ? zone.category : null;
  const moved = !(Math.hypot(x - last.x, z - last.z) < 0.05) || Math.abs(heading - last.heading) > 5;
  const due = now - last.at > PRESENCE_KEEPALIVE_MS; // the console tells a quiet room from a closed one
  if (!moved && !due && category === last.zone && !last.said) return;
  const update = {
    x: Math.round(x * 1000) / 1000,
    z: Math.round(z * 1000) / 1000,
    heading: Math.round(heading * 10) / 10,
    zone: category,
  };
  if (last.said) update.utterance = last.said;
  if (room.socket.notify("presence", update)) {
    room.presence = { at: now, x, z, heading, zone: category, said: null };
    savePose();
  }
}

// ---------------------------------------------------------------- what the participant sees

const WAITING = {
  assign: () => [_("Welcome"), _("The experimenter will seat the next participant in a moment.")],
  wait: () => [_("Please use the tablet"), _("Fill in the questionnaire on the tablet; the room goes on afterwards.")],
  done: () => [_("Thank you!"), _("You have finished the study.")],
  none: () => [_("The session has ended"), _("Please tell the experimenter.")],
};

function render() {
  const state = room.state;
  const label = el("run-label");
  if (state && state.session && sessionRunning()) {
    const s = state.session;
    const session = _("Session %(number)s", { number: s.number });
    const run = state.run ? _("run %(number)s of %(runs)s", { number: state.run.number, runs: s.runs }) : "";
    if (s.familiarisation) show(label, "Practice run (not counted)");
    else put(label, [session, run].filter(Boolean).join(" · "));
    label.classList.toggle("practice", s.familiarisation);
  } else {
    show(label, "Escape room");
    label.classList.remove("practice");
  }
  if (room.layout && room.scene) {
    for (const zone of room.layout.zones) room.scene.setZoneState(zone.category, zoneState(zone.category));
  }
  if (!state || canWalk()) {
    if (state) hideNotice();
    return;
  }
  const action = state.expected.action;
  // Only once no session runs: a running one whose floor plan is still loading (a reload's
  // state can come first) is this room's to show, and would otherwise be left and come back.
  if (ONLINE && action !== "start_session" && !sessionRunning()) {
    leaveRoom(); // a questionnaire, the end, or a withdrawal: /online knows which page
    return;
  }
  // A card in front of the room: the last reply's caption goes (it would linger under the card).
  hideCaption();
  if (action === "start_session") {
    const next = state.expected.session;
    const title = next === 0 ? _("A practice run comes first") : _("Session %(number)s comes next", { number: next });
    if (ONLINE) showNotice(title, _("Start when you are ready. The rules:"), { rules: true, start: true });
    else showNotice(title, _("The experimenter starts it in a moment. Meanwhile, the rules:"), { rules: true });
  } else {
    const [title, text] = WAITING[action] ? WAITING[action]() : [_("Please wait"), ""];
    showNotice(title, text, { rules: action === "assign" });
  }
  // The server's hint names the experimenter's next step: an online participant has none.
  showDetail(ONLINE ? "" : serverWords(state.expected.message));
  if (ONLINE && action === "start_session") el("start-session").focus();
}

function zoneState(category) {
  const state = room.state;
  if (!state || !state.run) return "pending";
  if (room.question && room.question.category === category) return "asked";
  if (state.run.answered.includes(category) || needsExit()) return "done";
  return "pending";
}

function showNotice(title, text, { rules = false, form = false, forget = false, start = false } = {}) {
  el("notice").hidden = false;
  el("start-session").hidden = !start;
  put(el("notice-title"), title);
  put(el("notice-text"), text);
  el("rules").hidden = !(rules && el("rules").childElementCount > 0);
  el("key-form").hidden = !form;
  // Not on the participant's cards: one click would close the room for the day.
  el("forget-key").hidden = ONLINE || form || !room.key || !(forget || options.has("setup"));
  if (form) el("key-input").focus();
}

/** Put ``text``, already in the current language (or staff English), in ``node``: no longer a
 * marked sentence, so a language switch leaves it (render() draws the participant's anew). */
function put(node, text) {
  delete node.dataset.t;
  delete node.dataset.tValues;
  node.textContent = text;
}

function hideNotice() {
  el("notice").hidden = true;
}

/** The server's own words (a refusal's detail, its hint of what comes next) are English, for the
 * experimenter: shown to English rooms only, never to a participant in another language. */
function serverWords(text) {
  return language() === "en" ? text || "" : "";
}

function showDetail(text) {
  el("notice-detail").textContent = text;
}

function setConnection(status) {
  const badge = el("connection");
  if (status === "connecting") show(badge, "Connecting…");
  else if (status === "online") show(badge, "Connected");
  else if (status === "offline") show(badge, "Offline");
  else show(badge, "Closed");
  el("connection").dataset.status = status;
  // shown from a lost connection until the next is up (not while the very first one opens)
  el("offline").hidden = !(status === "offline" || (status === "connecting" && room.everOnline));
}

// ---------------------------------------------------------------- starting, keys and refusals

function askForKey(problem) {
  showNotice(staff("Open the escape room"), staff("Enter a device key of this station to connect it."), { form: true });
  el("key-error").textContent = problem || "";
}

// An online participant's time away from the room (another tab or window in front) is part of
// their data quality (app/services/participants/data_quality.py): each hidden spell is reported
// when the room is seen again, or when the page goes away while hidden.
function reportTimeAway() {
  let hiddenSince = document.hidden ? Date.now() : null;
  const report = () => {
    if (hiddenSince === null) return;
    const seconds = Math.max(0, Date.now() - hiddenSince) / 1000;
    hiddenSince = null;
    navigator.sendBeacon(root.dataset.away, new URLSearchParams({ seconds: seconds.toFixed(3) }));
  };
  document.addEventListener("visibilitychange", () => {
    if (document.hidden) hiddenSince = Date.now();
    else report();
  });
  window.addEventListener("pagehide", report);
}
if (ONLINE && root.dataset.away) reportTimeAway();

const LONGEST_GOODBYE_MS = 8000; // the most a leaving room waits for the robot's last line

/** Go to /online, which knows the page that comes next. The robot's line being said (the
 * reply to a session's last answer) is heard to its end first, with its caption: leaving the
 * page would cut it off. */
async function leaveRoom() {
  if (room.leaving) return;
  room.leaving = true;
  if (room.socket) room.socket.stop();
  if (room.speaking) {
    const bound = new Promise((resolve) => setTimeout(resolve, LONGEST_GOODBYE_MS));
    await Promise.race([room.speaking, bound]);
  }
  location.assign(root.dataset.leave);
}

async function startSession() {
  const button = el("start-session");
  button.disabled = true;
  try {
    const response = await fetch(root.dataset.start, { method: "POST", credentials: "same-origin" });
    // 409: it had started already (a second tab) or is not theirs to start: /online tells which.
    if (!response.ok && response.status !== 409) throw new Error(String(response.status));
    if (response.status === 409) leaveRoom();
  } catch (error) {
    showDetail(_("The session did not start: please try again."));
  } finally {
    button.disabled = false;
  }
}

function refuse(problem) {
  if (ONLINE) {
    leaveRoom(); // their key was revoked: the time limit passed, or staff ended it
    return;
  }
  localStorage.removeItem(stores.key);
  room.key = "";
  if (room.socket) room.socket.stop();
  room.socket = null;
  room.state = null; // nothing may be walked or asked until a key connects again
  room.promptInFlight = null;
  room.resumed = false;
  closeQuestion();
  if (room.listener.close) room.listener.close(); // its socket and the microphone too
  room.listener = NOT_LISTENING;
  el("captions").hidden = true;
  show(el("run-label"), "Escape room");
  el("run-label").classList.remove("practice");
  showDetail("");
  setConnection("closed");
  askForKey(problem);
}

async function loadRoom() {
  const key = room.key;
  let response;
  room.loading = true;
  try {
    response = await fetch(`${API}/room`, {
      headers: { Authorization: `Bearer ${key}` },
      cache: "no-store",
    });
  } catch {
    setTimeout(() => {
      room.loading = false;
      if (room.key === key && !room.scene) loadRoom(); // the network: try again
    }, 2000);
    return;
  }
  const body = await response.json().catch(() => ({}));
  room.loading = false;
  // Checked after the last await: the station's hello may have refused this key (a key of another
  // station) while the body was still being read, and its room must not be drawn then.
  if (room.key !== key || room.scene) return; // answered for a key (or a room) no longer in use
  if (response.status === 401) {
    refuse(staff("The room was closed: this key is unknown or has been revoked. Ask an admin for a new key on the Stations page."));
    return;
  }
  if (response.status === 409) {
    showNotice(staff("No study here yet"), staff("This station runs no study yet: the experimenter seats a participant on its console first."), { forget: true });
    return; // a participant_assigned push loads it
  }
  if (!response.ok) {
    showNotice(staff("The room could not be loaded"), body.detail || staff(`The server answered ${response.status}.`), { forget: true });
    setTimeout(loadRoom, 5000);
    return;
  }
  buildRoom(body);
}

/** Speak the seated participant's language: the page's words, then (as the server now answers
 * in it) the study's rules, the request to answer again and how the room listens. */
async function switchLanguage(code) {
  await useLanguage(code);
  render();
  if (room.key && room.layout) {
    loadSpeech();
    refreshRules();
  }
}

async function refreshRules() {
  try {
    const response = await fetch(`${API}/room`, {
      headers: { Authorization: `Bearer ${room.key}` },
      cache: "no-store",
    });
    if (response.ok) showRules((await response.json()).rules);
  } catch {
    // the network: the rules stay as they were until the next load
  }
}

function showRules(rules) {
  el("rules").replaceChildren(...rules.map((rule) => Object.assign(document.createElement("li"), { textContent: rule })));
}

function speechSettings() {
  return room.speech || { listen_seconds: 8, reprompt: ASK_AGAIN(), cloud_recognizer: false };
}

/** Read the study's [speech] settings and choose how the room listens: the trustlab server's
 * offline recogniser, or the browser's own only where the protocol allows a cloud recogniser. */
async function loadSpeech() {
  const key = room.key;
  try {
    const response = await fetch(`${API}/speech`, {
      headers: { Authorization: `Bearer ${key}` },
      cache: "no-store",
    });
    if (!response.ok || room.key !== key) return;
    room.speech = await response.json();
  } catch {
    return; // the network: the room listens with the defaults once it is back and reloaded
  }
  room.listener.stop();
  if (room.listener.close) room.listener.close();
  const speech = room.speech;
  const phrases = { yes: speech.yes, no: speech.no, english: (speech.language || "en").startsWith("en") };
  const browser = new Listener(LISTEN && speech.cloud_recognizer, phrases);
  if (browser.available) {
    room.listener = browser;
  } else if (room.speech.offline_recognition === false) {
    room.listener = NOT_LISTENING; // the server knows no words of this language: buttons
  } else {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const url = `${scheme}://${location.host}${API}/audio`;
    room.listener = new ServerListener(url, () => room.key, LISTEN);
  }
}

/** The server's recording of one of the study's lines, for a browser without voices: its WAV,
 * "unavailable" when the server cannot synthesise (captions only), or null. */
async function serverLine(text) {
  try {
    const response = await fetch(`${API}/speech/audio?text=${encodeURIComponent(text)}`, {
      headers: { Authorization: `Bearer ${room.key}` },
    });
    if (response.status === 503) return "unavailable";
    return response.ok ? await response.arrayBuffer() : null;
  } catch {
    return null;
  }
}

/** Take the drawn room down (a key of another station drew that station's room). */
function closeRoom() {
  if (room.scene) room.scene.dispose();
  room.scene = null;
  room.layout = null;
  room.study = null;
  room.pose = null;
}

function buildRoom(description) {
  if (room.scene) return;
  if (!webglAvailable()) {
    showNotice(staff("This browser cannot draw the room"), staff("WebGL is switched off or missing. Use a current Chrome, Edge or Firefox, or the console's Wizard-of-Oz mode."));
    return;
  }
  room.layout = description.layout;
  room.study = description.study;
  room.segments = wallSegments(room.layout);
  showRules(description.rules);
  room.scene = new RoomScene(el("view"), room.layout, {
    robot: options.get("robot"),
    scale: options.has("scale") ? Number(options.get("scale")) : undefined,
  });
  restorePose();
  if (!room.pose) room.pose = startPose(room.layout);
  room.scene.start(frame);
  loadSpeech();
  offerHeadset();
  render();
}

function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const query = root.dataset.socketQuery || ""; // a preview's condition
  room.socket = new StationSocket(`${scheme}://${location.host}${API}/ws${query}`, room.key, {
    status: setConnection,
    refused: () => refuse(staff("The room was closed: this device's key was revoked or is unknown. Ask an admin for a new key on the Stations page.")),
    hello: (message) => {
      room.everOnline = true;
      if (message.station !== station) {
        room.socket.stop();
        localStorage.removeItem(stores.key);
        room.key = "";
        closeRoom();
        showNotice(staff("This key is for another station"), staff(`It belongs to station ${message.station}: open /stations/${message.station}/room, or enter a key of ${station}.`), { form: true });
        return;
      }
      if (!room.resumed) {
        room.resumed = true;
        resumeStoredAnswer(); // first: the question it answers is not asked again meanwhile
      }
      applyState(message.state);
    },
    event: (message) => {
      applyState(message.state);
    },
  });
  room.socket.connect();
}

function start() {
  if (!room.key) {
    askForKey("");
    return;
  }
  showNotice(_("Escape room"), _("Connecting…"));
  loadRoom();
  connect();
}

// ---------------------------------------------------------------- controls

const KEYS = {
  ArrowUp: "forward", KeyW: "forward", ArrowDown: "back", KeyS: "back",
  ArrowLeft: "turn-left", KeyA: "turn-left", ArrowRight: "turn-right", KeyD: "turn-right",
  KeyQ: "strafe-left", KeyE: "strafe-right",
};

function typing(event) {
  return event.target instanceof HTMLInputElement || event.target instanceof HTMLTextAreaElement;
}

window.addEventListener("keydown", (event) => {
  if (typing(event)) return;
  if (KEYS[event.code]) {
    room.held.add(KEYS[event.code]);
    event.preventDefault();
  } else if (!event.repeat && !event.ctrlKey && !event.metaKey && !event.altKey) {
    // The keys the catalogue names (Y/N, J/N in Swedish and German), whatever the keyboard's layout.
    const key = event.key.toUpperCase();
    if (key === answerKey("yes")) answer("yes", "key");
    else if (key === answerKey("no")) answer("no", "key");
  }
});
window.addEventListener("keyup", (event) => {
  if (KEYS[event.code]) room.held.delete(KEYS[event.code]);
});
window.addEventListener("blur", () => room.held.clear());
// The pose is saved with each presence report (at most twice a second); save the exact one when
// the page goes away, so a reload puts the participant back where they stood, not where they
// were half a second earlier.
window.addEventListener("pagehide", () => {
  if (room.pose && runKey()) savePose();
});
window.addEventListener("resize", () => room.scene && room.scene.resize());

el("start-session").addEventListener("click", startSession);
el("answer-yes").addEventListener("click", () => answer("yes", "button"));
el("answer-no").addEventListener("click", () => answer("no", "button"));

for (const pad of document.querySelectorAll("[data-move]")) {
  const move = pad.dataset.move;
  pad.addEventListener("pointerdown", (event) => {
    pad.setPointerCapture(event.pointerId);
    room.held.add(move);
  });
  for (const end of ["pointerup", "pointercancel", "lostpointercapture"]) {
    pad.addEventListener(end, () => room.held.delete(move));
  }
}
if (matchMedia("(pointer: coarse)").matches || options.has("pads")) {
  el("pads").hidden = false;
  root.classList.add("with-pads"); // the yes/no controls move right, clear of the pads
}

el("view").addEventListener("pointermove", (event) => {
  if (event.buttons === 1 && event.pointerType === "mouse") room.dragged += event.movementX * DRAG_DEGREES;
});

el("key-form").addEventListener("submit", (event) => {
  event.preventDefault();
  const key = el("key-input").value.trim();
  if (!key.startsWith("tlk_")) {
    el("key-error").textContent = staff("A device key starts with tlk_.");
    return;
  }
  localStorage.setItem(stores.key, key);
  room.key = key;
  el("key-input").value = "";
  el("key-form").hidden = true;
  start();
});

el("forget-key").addEventListener("click", () => {
  if (confirm(staff("Forget this device's key? The room closes until a key is entered again."))) refuse("");
});

async function offerHeadset() {
  if (!navigator.xr) return;
  for (const [mode, button] of [["immersive-ar", "enter-ar"], ["immersive-vr", "enter-vr"]]) {
    const supported = await navigator.xr.isSessionSupported(mode).catch(() => false);
    if (!supported) continue;
    el("headset").hidden = false;
    el(button).hidden = false;
    el(button).addEventListener("click", () => {
      room.scene.enterHeadset(mode, root).catch((error) => showDetail(staff(`The headset session did not start: ${error.message}`)));
    });
  }
}

// Read-only views for the browser tests and bench/room.py (nothing here changes the room).
window.trustlabRoom = {
  get pose() {
    return room.pose ? { ...room.pose } : null;
  },
  get state() {
    return room.state;
  },
  get question() {
    return room.question ? { ...room.question } : null;
  },
  /** The last caption said ({kind, text}), shown or since cleared by a card in front of it. */
  get said() {
    return room.said ? { ...room.said } : null;
  },
  /** Whether the robot is still saying its last spoken line. */
  get saying() {
    return room.saying;
  },
  get frames() {
    return room.frames;
  },
  get renderScale() {
    return room.scene ? room.scene.renderScale : null;
  },
  get ready() {
    return Boolean(room.scene && room.state && room.socket && room.socket.online);
  },
  /** Whether the room's description is still being fetched or read. */
  get loading() {
    return Boolean(room.loading);
  },
  /** How the room listens: "server", "browser", or null (not yet, or not at all). */
  get listener() {
    if (room.listener === NOT_LISTENING) return null;
    return room.listener instanceof ServerListener ? "server" : "browser";
  },
};

start();
