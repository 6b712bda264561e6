// The pages' connection to the HMI node: one WebSocket, reconnected by itself.
// No framework, no build step: this file, worker.js, operator.js and console.js are all the
// code (the console's charts are uPlot's, vendor/).
'use strict';
const HMI = (() => {
  const NO_CELL = 'no connection to the cell';
  // the HMI answers but refuses this page's token (it was restarted with new tokens, or the
  // cookie is gone): waiting would never connect
  const REFUSED = 'access refused: open this page again with the link that carries its token';
  const WATCHDOG_MS = 15000;   // the server sends something at least every 5 s

  function text(id, value) {
    const element = document.getElementById(id);
    if (element && element.textContent !== value) element.textContent = value;
  }

  // connect(view, {view(message, client), reply(message, client), feed(message), down()})
  function connect(view, handlers) {
    const connection = document.getElementById('connection');
    let socket = null, client = null, backoff = 250, watchdog = null, opened = false;

    function show(state, words) {
      connection.dataset.state = state;
      text('connection', words);
    }
    function arm() {
      clearTimeout(watchdog);
      watchdog = setTimeout(() => { if (socket) socket.close(); }, WATCHDOG_MS);
    }
    function open() {
      const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
      socket = new WebSocket(`${scheme}://${location.host}/ws?view=${view}`);
      opened = false;
      socket.onopen = () => { backoff = 250; opened = true; arm(); };
      socket.onmessage = (event) => {
        arm();
        let message;
        try { message = JSON.parse(event.data); } catch (error) { return; }
        if (message.type === 'hello') {
          client = message.client;
        } else if (message.type === 'view') {
          show(message.cell ? 'connected' : 'no-cell', message.connection || NO_CELL);
          handlers.view(message, client);
        } else if (message.type === 'feed') {
          if (handlers.feed) handlers.feed(message);
        } else if (message.type !== 'tick' && handlers.reply) {
          handlers.reply(message, client);
        }
      };
      socket.onclose = () => {
        clearTimeout(watchdog);
        socket = null;
        client = null;
        // a refused handshake looks like no server at all: ask the page itself why (a page
        // already refused keeps saying so until the answer changes: no flicker)
        if (opened || connection.dataset.state !== 'refused') show('disconnected', NO_CELL);
        if (!opened) {
          fetch(location.pathname, {cache: 'no-store'}).then((response) => {
            if (opened) return;
            if (response.status === 401 || response.status === 403) show('refused', REFUSED);
            else show('disconnected', NO_CELL);
          }, () => { if (!opened) show('disconnected', NO_CELL); });
        }
        if (handlers.down) handlers.down();
        setTimeout(open, backoff + Math.random() * 250);
        backoff = Math.min(backoff * 2, 4000);
      };
    }
    open();
    return {
      send(message) {
        if (!socket || socket.readyState !== WebSocket.OPEN) return false;
        socket.send(JSON.stringify(message));
        return true;
      },
    };
  }

  function band(distance) {
    const element = document.getElementById('distance-band');
    if (!element) return;
    const d = distance || {level: null, text: 'distance unknown', colour: '#888888'};
    element.dataset.level = d.level === null ? 'none' : String(d.level);
    element.style.background = d.colour;
    text('distance', d.text);
  }

  return {connect, text, band, NO_CELL};
})();
