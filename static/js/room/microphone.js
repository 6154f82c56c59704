// Voice answers recognised on the trustlab server: the microphone, downsampled to 16 kHz in an
// AudioWorklet (pcm16k.js), streamed over the audio socket (/api/v1/station/audio) while a
// question is open; the server recognises the yes or no offline and records it, so the voice
// never leaves the lab (docs/escape-room.md, "Answers by voice").
//
// Nothing is streamed between questions: the microphone stays open once granted (asking again
// for each question would show the browser's prompt or indicator every time), but its samples
// are dropped unless the server has said it is listening for an answer.

const HELLO_TIMEOUT_MS = 8000;
const DECISION_TIMEOUT_MS = 8000; // after "stop": the server's decision, or the socket is dropped

/** The microphone as 16 kHz 16-bit PCM chunks (ArrayBuffers of 100 ms). */
export class Microphone {
  constructor() {
    this.context = null;
    this.stream = null;
    this.onChunk = null;
    this.refused = false;
  }

  get supported() {
    return Boolean(navigator.mediaDevices && navigator.mediaDevices.getUserMedia && window.AudioWorkletNode);
  }

  /** Open it (the browser asks the participant's permission the first time); false when it
   * cannot be had: no microphone, a refused permission, or a browser without AudioWorklet. */
  async open() {
    if (this.context) {
      if (this.context.state === "suspended") await this.context.resume().catch(() => {});
      return true;
    }
    if (this.refused || !this.supported) return false;
    try {
      this.stream = await navigator.mediaDevices.getUserMedia({
        audio: { channelCount: 1, echoCancellation: true, noiseSuppression: true, autoGainControl: true },
      });
      const context = new AudioContext();
      await context.audioWorklet.addModule(new URL("./pcm16k.js", import.meta.url));
      const source = context.createMediaStreamSource(this.stream);
      const node = new AudioWorkletNode(context, "pcm16k", { numberOfOutputs: 0 });
      node.port.onmessage = (event) => this.onChunk && this.onChunk(event.data);
      source.connect(node);
      if (context.state === "suspended") await context.resume().catch(() => {});
      this.context = context;
      return true;
    } catch {
      this.refused = true; // the buttons and keys remain; not asked again in this page
      this.close();
      return false;
    }
  }

  close() {
    if (this.stream) for (const track of this.stream.getTracks()) track.stop();
    if (this.context) this.context.close().catch(() => {});
    this.stream = null;
    this.context = null;
  }
}

/** Listens for one yes/no answer at a time through the trustlab server's recogniser. */
export class ServerListener {
  /**
   * @param {string} url ws:// or wss:// URL of /api/v1/station/audio
   * @param {() => string} key the station's device key (read when connecting)
   * @param {boolean} enabled false: never listens (?listen=off)
   */
  constructor(url, key, enabled = true) {
    this.url = url;
    this.key = key;
    this.enabled = enabled;
    this.microphone = new Microphone();
    this.microphone.onChunk = (chunk) => this._chunk(chunk);
    this.socket = null;
    this.ready = null; // a promise of the greeted socket
    this.active = null; // {id, settle, streaming, timer}
    this.nextId = 1;
    this.calls = 0; // listen() calls and stops: a stale one gives up
    this.unavailable = false; // the server said it cannot recognise (503)
  }

  get available() {
    return this.enabled && !this.unavailable && !this.microphone.refused && this.microphone.supported;
  }

  /** Listen for the answer to step ``stepId`` for at most ``seconds``. Resolves with null (nothing
   * heard: silence, no microphone, no server, or :meth:`stop`) or ``{answer, transcript,
   * confidence, engine, recorded}``: ``recorded`` is the server's reply when it recorded a clear
   * answer; ``answer`` is null for anything unclear (the room asks again). */
  async listen(stepId, { seconds = 8, idempotencyKey } = {}) {
    this.stop();
    const call = ++this.calls;
    if (!this.available || !(await this.microphone.open())) return null;
    const socket = await this._connect();
    // stopped (or listening again) while the permission prompt or the connection was pending
    if (!socket || call !== this.calls) return null;
    return new Promise((resolve) => {
      const id = this.nextId++;
      const active = { id, streaming: false, timer: null, settle: null };
      active.settle = (value) => {
        if (this.active !== active) return;
        this.active = null;
        clearTimeout(active.timer);
        resolve(value);
      };
      this.active = active;
      const start = { type: "start", id, step_id: stepId };
      if (idempotencyKey) start.idempotency_key = idempotencyKey;
      socket.send(JSON.stringify(start));
      active.timer = setTimeout(() => {
        // listening time is up: the server decides on what it has (silence, usually)
        if (this.active !== active) return;
        active.streaming = false;
        this._send({ type: "stop", id });
        active.timer = setTimeout(() => this._drop(), DECISION_TIMEOUT_MS);
      }, seconds * 1000);
    });
  }

  /** Stop listening; the server drops the audio unheard. */
  stop() {
    this.calls += 1; // a listen still waiting for the microphone or the socket gives up
    const active = this.active;
    if (!active) return;
    active.settle(null);
    this._send({ type: "cancel", id: active.id });
  }

  /** Stop for good: the socket and the microphone are closed (the room was closed). */
  close() {
    this.stop();
    this.enabled = false;
    if (this.socket) this.socket.close(1000, "room closed");
    this.microphone.close();
  }

  _chunk(buffer) {
    const active = this.active;
    if (active && active.streaming && this.socket && this.socket.readyState === WebSocket.OPEN) {
      this.socket.send(buffer);
    }
  }

  _send(message) {
    if (this.socket && this.socket.readyState === WebSocket.OPEN) this.socket.send(JSON.stringify(message));
  }

  _connect() {
    if (this.ready) return this.ready;
    this.ready = new Promise((resolve) => {
      let socket;
      try {
        socket = new WebSocket(this.url);
      } catch {
        this.ready = null;
        resolve(null);
        return;
      }
      socket.binaryType = "arraybuffer";
      const timer = setTimeout(() => {
        socket.close();
      }, HELLO_TIMEOUT_MS);
      socket.onopen = () => socket.send(JSON.stringify({ type: "auth", key: this.key() }));
      socket.onmessage = (frame) => {
        let message;
        try {
          message = JSON.parse(frame.data);
        } catch {
          return;
        }
        if (message.type === "hello") {
          clearTimeout(timer);
          this.socket = socket;
          resolve(socket);
        } else {
          this._receive(message);
        }
      };
      socket.onclose = () => {
        clearTimeout(timer);
        if (this.socket === socket) this.socket = null;
        this.ready = null;
        resolve(null);
        if (this.active) this.active.settle(null); // the next question connects again
      };
      socket.onerror = () => {}; // onclose follows
    });
    return this.ready;
  }

  _drop() {
    if (this.socket) this.socket.close();
  }

  _receive(message) {
    const active = this.active;
    if (!active || message.id !== active.id) return; // about an answer no longer listened for
    const heard = message.heard || { transcript: "", confidence: 0, engine: "" };
    switch (message.type) {
      case "listening":
        active.streaming = true;
        break;
      case "answer":
        active.settle({ ...heard, answer: message.data.answer, recorded: message.data });
        break;
      case "unclear":
        // Silence counts as nothing heard. Otherwise the room asks again without showing the
        // words: an offline grammar's transcript is the phrase nearest to what was said, not it.
        active.settle(heard.transcript ? { ...heard, transcript: "", answer: null, recorded: null } : null);
        break;
      case "error":
        if (message.status === 503) this.unavailable = true; // no recogniser: the buttons remain
        if (message.status === 413) {
          active.settle({ transcript: "", confidence: 0, engine: "", answer: null, recorded: null });
        } else {
          active.settle(null);
        }
        break;
      default:
        break;
    }
  }
}
