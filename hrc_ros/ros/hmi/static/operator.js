// The operator's page: the cell, the task queue and history, the task form, the belief, the
// fail-safe reasons, the robot arm.
'use strict';
(() => {
  const form = document.getElementById('task-form');
  const result = document.getElementById('task-result');
  let sent = 0;   // orders sent from this page; the server echoes the number as ref

  function item(parent, tag, words) {
    const element = document.createElement(tag);
    element.textContent = words;
    parent.appendChild(element);
    return element;
  }

  function bars(belief) {
    const box = document.getElementById('belief');
    box.replaceChildren();
    if (!belief) { item(box, 'p', 'no belief yet').className = 'hint'; return; }
    for (const [name, values] of [['motivation', belief.motivation], ['aggression', belief.aggression]]) {
      values.forEach((p, i) => {
        const row = item(box, 'div', '');
        row.className = 'row';
        item(row, 'span', `${name} ${belief.levels[i]}`).className = 'name';
        const bar = item(row, 'span', '');
        bar.className = 'bar';
        item(bar, 'div', '').style.width = `${Math.round(100 * p)}%`;
        item(row, 'span', p.toFixed(2)).className = 'value';
      });
    }
  }

  function render(v) {
    HMI.text('epoch', v.epoch ? `epoch ${v.epoch}` : 'epoch -');
    HMI.text('action', v.action || HMI.NO_CELL);
    HMI.band(v.distance);
    const request = v.request;
    let words = '';
    if (request) {
      words = `request: ${request.text}`;
      if (request.answer !== null && request.answer !== undefined) {
        words += request.answer ? ' (accepted' : ' (declined';
        words += request.answered_by === 'elsewhere' ? ' elsewhere)' : ' on a page)';
      } else {
        words += ' (waiting for the answer)';
      }
    }
    HMI.text('request', words);
    const last = v.last_request;
    HMI.text('request-outcome', last ? `last request: ${last.text}: ${last.outcome_text}` : '');
    HMI.text('task', v.task ? v.task.text : 'no task state yet');
    const queue = v.queue || {};
    HMI.text('queue', queue.waiting === undefined || queue.waiting === null
      ? 'no report from the task manager yet'
      : `${queue.waiting} waiting; next ${queue.next}; ${queue.completed} completed`
        + (queue.waiting_for && queue.waiting_for !== 'none' ? `; waiting for ${queue.waiting_for}` : ''));
    const orders = document.getElementById('orders');
    orders.replaceChildren();
    for (const order of v.orders || []) {
      item(orders, 'li', `(${order.task.join(', ')}) from ${order.from}: ${order.text}`);
    }
    const body = document.querySelector('#history tbody');
    body.replaceChildren();
    for (const t of v.history || []) {
      const row = item(body, 'tr', '');
      for (const cell of [t.number, `(${t.task.join(', ')})`, t.nature, t.seen_epoch,
                          t.commit_epoch === null ? '-' : t.commit_epoch,
                          t.commit_epoch === null ? '-' : t.committed,
                          t.done_epoch === null ? '-' : t.done_epoch]) {
        item(row, 'td', String(cell));
      }
    }
    bars(v.belief);
    const fail = document.getElementById('fail-safe');
    const fs = v.fail_safe;
    fail.dataset.level = fs ? fs.level : 'none';
    HMI.text('fail-safe', !fs ? 'no report from the decision node yet'
      : fs.reasons.length ? `epoch ${fs.epoch}: ${fs.action} (fail-safe): ${fs.reasons.join('; ')}`
        : `epoch ${fs.epoch}: ${fs.action}, no fail-safe`);
    const robot = v.robot;
    HMI.text('robot', !robot ? 'robot side not running' : [
      robot.speed_override !== undefined ? `speed override ${Math.round(100 * robot.speed_override)}%` : null,
      robot.separation !== undefined ? `separation ${robot.separation.toFixed(3)} m` : null,
    ].filter(Boolean).join('; '));
    if (v.limits) {
      for (const name of ['priority', 'duration', 'nature']) {
        const input = form.elements[name];
        [input.min, input.max] = v.limits[name].map(String);
      }
    }
  }

  function showResult(status, words) {
    result.dataset.status = status;
    result.textContent = words;
  }

  const link = HMI.connect('operator', {
    view: render,
    reply(message) {
      if (message.type === 'order_result') {
        if (message.ref === sent) showResult(message.status, message.text);
      } else if (message.type === 'error') {
        showResult('refused', message.text);
      }
    },
  });

  form.addEventListener('submit', (event) => {
    event.preventDefault();
    const fields = {};
    for (const name of ['priority', 'duration', 'nature']) {
      const value = form.elements[name].value.trim();
      fields[name] = /^\d+$/.test(value) ? Number(value) : value;
    }
    sent += 1;
    if (link.send({type: 'order', ref: sent, ...fields})) {
      showResult('checking', 'sending...');
    } else {
      showResult('refused', 'no connection to the cell: nothing sent');
    }
  });
})();
