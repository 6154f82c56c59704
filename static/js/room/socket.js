// The station WebSocket as a room client uses it (docs/robot-integration.md, section 5): the key
// as the first message, requests matched to replies by id, pushes, heartbeats, and reconnection.
//
// Nothing acknowledged is lost and nothing is done twice: a request that had no reply when the
// connection dropped is sent again, unchanged, after the next ``hello`` (an answer keeps its
// idempotency key, so the server hands back the reply it stored; a prompt hands back the
// category's open step). A connection that stops answering is closed and replaced rather than
// trusted: a request unanswered for REPLY_TIMEOUT_MS, or the browser going offline, ends it.

const REPLY_TIMEOUT_MS = 8000;
const HELLO_TIMEOUT_MS = 10000; // a handshake or greeting that never comes: try again
const CLIENT_PING_MS = 5000;
export const CLOSE_UNAUTHENTICATED = 4401;

export class StationSocket {
  /**
   * @param {string} url ws:// or wss:// URL of /api/v1/station/ws
   * @param {string} key the station's device key
   * @param {object} on callbacks: hello(message), event(message), status("connecting"|"online"|
   *   "offline"), refused(reason) — the key is unknown or revoked (no reconnection after that)
   */
  constructor(url, key, on) {
    this.url = url;
    this.key = key;
    this.on = on;
    this.socket = null;
    this.nextId = 1;
    this.pending = new Map(); // id → {message, resolve, reject, sentAt}
    this.backoff = 200;
    this.stopped = false;
    this.online = false;
    this._timer = null;
    this._offline = () => this._drop();
    this._onlineAgain = () => this._reconnectSoon(0);
    window.addEventListener("offline", this._offline);
    window.addEventListener("online", this._onlineAgain);
  }

  connect() {
    if (this.stopped) return;
    this.on.status("connecting");
    let socket;
    try {
      socket = new WebSocket(this.url);
    } catch {
      this._reconnectSoon();
      return;
    }
    this.socket = socket;
    clearTimeout(this._helloTimer);
    this._helloTimer = setTimeout(() => {
      if (this.socket === socket && !this.online) this._drop();
    }, HELLO_TIMEOUT_MS);
    socket.onopen = () => socket.send(JSON.stringify({ type: "auth", key: this.key }));
    socket.onmessage = (frame) => this._receive(socket, frame.data);
    socket.onclose = (closed) => this._closed(socket, closed);
    socket.onerror = () => {}; // onclose follows and decides
  }

  /** Send a request; resolves with the reply's data, rejects with ``{status, detail}``. Kept
   * until answered, across reconnections. */
  request(type, fields = {}) {
    const id = this.nextId++;
    const message = { type, id, ...fields };
    return new Promise((resolve, reject) => {
      this.pending.set(id, { message, resolve, reject, sentAt: 0 });
      if (this.online) this._send(id);
    });
  }

  /** Send a message that only matters now (the participant's position): not kept for later,
   * and its reply is not awaited. */
  notify(type, fields = {}) {
    if (!this.online) return false;
    const message = { type, id: `n${this.nextId++}`, ...fields };
    this.socket.send(JSON.stringify(message));
    return true;
  }

  /** Close for good: nothing is resent, and whatever waited for a reply is told so. */
  stop() {
    this.stopped = true;
    this.online = false;
    clearTimeout(this._timer);
    clearTimeout(this._helloTimer);
    clearInterval(this._pinger);
    for (const entry of this.pending.values()) entry.reject({ status: 0, detail: "the room was closed" });
    this.pending.clear();
    window.removeEventListener("offline", this._offline);
    window.removeEventListener("online", this._onlineAgain);
    if (this.socket) this.socket.close(1000, "room closed");
  }

  _send(id) {
    const entry = this.pending.get(id);
    if (!entry || !this.online) return;
    entry.sentAt = performance.now();
    this.socket.send(JSON.stringify(entry.message));
  }

  _receive(socket, raw) {
    if (socket !== this.socket) return;
    let message;
    try {
      message = JSON.parse(raw);
    } catch {
      return;
    }
    this.lastHeard = performance.now();
    switch (message.type) {
      case "hello": {
        this.online = true;
        this.backoff = 200;
        clearTimeout(this._helloTimer);
        const unanswered = [...this.pending.keys()].sort((a, b) => a - b);
        this.on.status("online");
        this._startPinging();
        this.on.hello(message); // may send requests of its own: those go out as they are made
        for (const id of unanswered) this._send(id);
        break;
      }
      case "result":
      case "error": {
        const entry = this.pending.get(message.id);
        if (!entry) break; // a notify's reply, or an answer to a request resent twice
        this.pending.delete(message.id);
        if (message.type === "result") entry.resolve(message.data);
        else entry.reject({ status: message.status, detail: message.detail });
        break;
      }
      case "event":
        this.on.event(message);
        break;
      case "ping":
        socket.send(JSON.stringify({ type: "pong" }));
        break;
      default:
        break;
    }
  }

  _startPinging() {
    clearInterval(this._pinger);
    this._pinger = setInterval(() => {
      if (!this.online) return;
      const now = performance.now();
      const overdue = [...this.pending.values()].some(
        (entry) => entry.sentAt && now - entry.sentAt > REPLY_TIMEOUT_MS,
      );
      if (overdue || now - this.lastHeard > REPLY_TIMEOUT_MS + CLIENT_PING_MS) {
        this._drop();
        return;
      }
      this.socket.send(JSON.stringify({ type: "ping", id: "keepalive" }));
    }, CLIENT_PING_MS);
  }

  /** Give up on the current connection (it will be replaced). */
  _drop() {
    if (this.socket) {
      const socket = this.socket;
      this._closed(socket, { code: 1006, reason: "connection lost" });
      try {
        socket.close();
      } catch {
        // already closed
      }
    }
  }

  _closed(socket, closed) {
    if (socket !== this.socket) return;
    this.socket = null;
    this.online = false;
    clearInterval(this._pinger);
    clearTimeout(this._helloTimer);
    if (this.stopped) return;
    if (closed.code === CLOSE_UNAUTHENTICATED) {
      this.stopped = true;
      this.on.refused(closed.reason || "unknown or revoked device key");
      return;
    }
    this.on.status("offline");
    this._reconnectSoon();
  }

  _reconnectSoon(delay) {
    if (this.stopped || this.socket) return;
    clearTimeout(this._timer);
    const wait = delay ?? this.backoff * (0.5 + Math.random() / 2);
    this.backoff = Math.min(this.backoff * 2, 5000);
    this._timer = setTimeout(() => {
      if (!this.socket) this.connect();
    }, wait);
  }
}
