// The worker's page: what the robot does, its request, Accept and Decline.
'use strict';
(() => {
  const accept = document.getElementById('accept');
  const decline = document.getElementById('decline');
  const box = document.getElementById('request-box');
  const motivation = document.getElementById('motivation');
  const SHORT = {already_answered: 'Already answered', closed: 'Too late', stale: 'Changed',
                 no_request: 'No request', no_cell: 'No connection', show_only: 'Display only',
                 busy: 'Busy: try again', bad: 'Not sent'};
  let view = null, client = null, pending = null;
  const answered = new Set();   // requests this page's answer was sent for
  const notes = new Map();   // request id -> {button, label, text} of a refused or sent tap

  function answeredWords(request) {
    const given = request.answer ? 'accepted' : 'declined';
    if (request.answered_by === client) return `you answered: ${given}`;
    if (request.answered_by === 'elsewhere') return `answered elsewhere: ${given}`;
    return `answered on another screen: ${given}`;
  }

  function name(button, request) {
    // the accessible name: what the button says and what it answers
    const words = request ? `${button.textContent}: ${request.text}`
      : `${button.textContent} (no request open)`;
    if (button.getAttribute('aria-label') !== words) button.setAttribute('aria-label', words);
  }

  function render() {
    const v = view || {};
    const request = v.request || null;
    document.getElementById('action-label').hidden = !v.cell;
    HMI.text('action', v.action || HMI.NO_CELL);
    HMI.band(v.distance);
    motivation.hidden = !v.motivation;
    HMI.text('motivation', v.motivation || '');
    HMI.text('request', request ? request.text : '');
    box.dataset.state = request ? (request.answerable ? 'open' : 'answered') : 'none';
    const last = v.last_request;
    HMI.text('request-outcome', !request && last ? `${last.text}: ${last.outcome_text}` : '');
    let note = '';
    accept.textContent = 'Accept';
    decline.textContent = 'Decline';
    accept.classList.remove('chosen');
    decline.classList.remove('chosen');
    if (!request) {
      accept.disabled = decline.disabled = true;
      accept.title = decline.title = 'no open request';
    } else {
      const mine = notes.get(request.id);
      const waiting = pending === request.id;
      accept.disabled = decline.disabled = waiting || !request.answerable
        || answered.has(request.id);
      accept.title = decline.title = '';
      if (request.answer !== null) {
        (request.answer ? accept : decline).classList.add('chosen');
        (request.answer ? accept : decline).textContent = request.answer ? 'Accepted' : 'Declined';
        note = answeredWords(request);
      } else if (!v.worker_answers) {
        note = 'this page only shows the answers';
      }
      if (waiting) note = 'sending...';
      if (mine) {
        mine.button.textContent = mine.label;
        mine.button.title = mine.text;
        note = mine.text;
      }
    }
    HMI.text('answer-note', note);
    name(accept, request);
    name(decline, request);
  }

  const link = HMI.connect('worker', {
    view(message, id) { view = message; client = id; render(); },
    reply(message) {
      if (message.type === 'answer_result') {
        if (pending === message.request) pending = null;
        const button = message.accept === false ? decline : accept;
        notes.set(message.request, {button, text: message.text,
                                    label: message.ok ? button.textContent : (SHORT[message.code] || 'Not sent')});
        if (notes.size > 64) notes.delete(notes.keys().next().value);
        if (message.ok) {
          notes.delete(message.request);
          answered.add(message.request);
          if (answered.size > 64) answered.delete(answered.values().next().value);
        }
        render();
        if (message.ok && view && view.request && view.request.answer === null) {
          HMI.text('answer-note', message.text);
        }
      } else if (message.type === 'error') {
        HMI.text('answer-note', message.text);
      }
    },
    down() { pending = null; view = null; render(); },
  });

  function tap(yes) {
    const request = view && view.request;
    if (!request || pending) return;
    pending = request.id;
    render();
    if (!link.send({type: 'answer', request: request.id, accept: yes})) {
      pending = null;
      notes.set(request.id, {button: yes ? accept : decline, label: 'No connection',
                             text: 'no connection to the cell: nothing sent'});
      render();
    }
  }
  accept.addEventListener('click', () => tap(true));
  decline.addEventListener('click', () => tap(false));
  render();
})();
