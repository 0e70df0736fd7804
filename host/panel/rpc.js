// The daemon's API over the WebSocket (host/web.py): JSON-RPC 2.0 as Moonraker frames it. Requests return promises;
// notifications (notify_<topic>) go to the handlers given; the connection is made again when it drops, until stop()
// (the daemon refuses this page's token: a person must give another).

export class Rpc {
  constructor({ onNotify, onOpen, onClose }) {
    this.onNotify = onNotify;
    this.onOpen = onOpen;
    this.onClose = onClose;
    this.nextId = 1;
    this.pending = new Map();
    this.socket = null;
    this.retryMs = 500;
    this.stopped = false;
  }

  stop() {
    this.stopped = true;
    if (this.socket) this.socket.close();
  }

  connect() {
    if (this.stopped) return;
    const scheme = location.protocol === "https:" ? "wss:" : "ws:";
    const socket = new WebSocket(`${scheme}//${location.host}/websocket`);
    this.socket = socket;
    socket.onopen = () => { this.retryMs = 500; this.onOpen(); };
    socket.onmessage = (message) => this.receive(message.data);
    socket.onclose = () => {
      for (const { reject } of this.pending.values()) {
        reject(new Error("no answer: the connection to the daemon was lost"));
      }
      this.pending.clear();
      this.onClose();
      setTimeout(() => this.connect(), this.retryMs);
      this.retryMs = Math.min(this.retryMs * 2, 5000);
    };
  }

  receive(text) {
    const message = JSON.parse(text);
    if (message.method && message.method.startsWith("notify_")) {
      this.onNotify(message.method.slice(7), message.params[0]);
      return;
    }
    const waiting = this.pending.get(message.id);
    if (!waiting) return;
    this.pending.delete(message.id);
    if (message.error) {
      const error = new Error(message.error.message);
      error.code = message.error.data && message.error.data.error;
      waiting.reject(error);
    } else {
      waiting.resolve(message.result);
    }
  }

  call(method, params = {}) {
    if (!this.socket || this.socket.readyState !== WebSocket.OPEN) {
      return Promise.reject(new Error("not sent: the daemon is not answering (no connection to it)"));
    }
    const id = this.nextId++;
    this.socket.send(JSON.stringify({ jsonrpc: "2.0", method, params, id }));
    return new Promise((resolve, reject) => this.pending.set(id, { resolve, reject }));
  }
}
