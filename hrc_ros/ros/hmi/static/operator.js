// The operator's console: the cell now, the figures of the shift, the timeline and the event
// log (console.js), the task form, the queue, the orders, the belief and the tasks seen.
'use strict';
(() => {
  const form = document.getElementById('task-form');
  const result = document.getElementById('task-result');
  const windowSelect = document.getElementById('window');
  let sent = 0;   // orders sent from this page; the server echoes the number as ref
  let last = null;
  const drawn = {};   // part -> the JSON it was last drawn from: a view redraws what changed

  function changed(part, value) {
    const text = JSON.stringify(value === undefined ? null : value);
    if (drawn[part] === text) return false;
    drawn[part] = text;
    return true;
  }

  function item(parent, tag, words) {
    const element = document.createElement(tag);
    element.textContent = words;
    parent.appendChild(element);
    return element;
  }

  function bars(belief) {
    const box = document.getElementById('belief');
    box.replaceChildren();
    if (!belief) { item(box, 'p', 'no estimate yet').className = 'hint'; return; }
    for (const [name, values] of [['motivation', belief.motivation], ['aggression', belief.aggression]]) {
      values.forEach((p, i) => {
        const row = item(box, 'div', '');
        row.className = 'row';
        item(row, 'span', `${name} ${belief.levels[i]}`).className = 'name';
        const bar = item(row, 'span', '');
        bar.className = 'bar';
        bar.setAttribute('aria-hidden', 'true');
        item(bar, 'div', '').style.width = `${Math.round(100 * p)}%`;
        item(row, 'span', `${Math.round(100 * p)}%`).className = 'value';
      });
    }
  }

  const KPI = {
    tasks_per_hour: (v) => v.toFixed(1),
    idle_share: (v) => `${v.toFixed(1)}%`,
    protective_stop_share: (v) => `${v.toFixed(1)}%`,
    refused_requests: (v) => String(v),
    min_separation: (v) => (v > 0 ? `${v.toFixed(2)} m` : `${v.toFixed(2)} m: contact`),
    fail_safe_epochs: (v) => String(v),
  };
  const NONE = {idle_share: 'no arm', protective_stop_share: 'no arm', min_separation: 'no arm',
                fail_safe_epochs: 'no report', tasks_per_hour: '-', refused_requests: '-'};

  function clock(ms) {
    return new Date(ms).toLocaleTimeString([], {hour: '2-digit', minute: '2-digit', second: '2-digit'});
  }

  function figures(all) {
    const box = document.getElementById('figures');
    const f = all ? all[windowSelect.value] : null;
    box.dataset.window = windowSelect.value;
    box.dataset.asOf = f ? String(f.as_of_ms) : '';
    box.dataset.since = f ? String(f.since_ms) : '';
    box.dataset.armSeconds = f ? String(f.arm_seconds) : '';
    for (const element of box.querySelectorAll('[data-kpi]')) {
      const name = element.dataset.kpi;
      const value = f ? f[name] : null;
      element.dataset.value = value === null || value === undefined ? '' : String(value);
      const shown = value === null || value === undefined ? NONE[name] : KPI[name](value);
      const dd = element.querySelector('dd');
      if (dd.textContent !== shown) dd.textContent = shown;
    }
    HMI.text('window-note', !f ? 'the shift begins when the robot first decides'
      : `from ${clock(f.since_ms)} to ${clock(f.as_of_ms)}: `
      + `${f.tasks_completed} task${f.tasks_completed === 1 ? '' : 's'} done`
      + (f.arm_seconds ? `, the arm measured for ${Math.round(f.arm_seconds)} s` : ''));
  }

  function render(v) {
    last = v;
    HMI.text('epoch', v.epoch ? `decision step ${v.epoch}` : 'no decision yet');
    document.getElementById('action-label').hidden = !v.cell;
    HMI.text('action', v.action || HMI.NO_CELL);
    const action = document.getElementById('action');
    action.title = v.action_code ? `the model's action: ${v.action_code}` : '';
    HMI.band(v.distance);
    const request = v.request;
    let words = '';
    if (request) {
      words = `the robot ${request.text}`;
      if (request.answer !== null && request.answer !== undefined) {
        words += request.answer ? ': accepted' : ': declined';
        words += request.answered_by === 'elsewhere' ? ' (answered elsewhere)' : ' (on a page)';
      } else {
        words += ": waiting for the worker's answer";
      }
    }
    HMI.text('request', words);
    const lastRequest = v.last_request;
    HMI.text('request-outcome', lastRequest
      ? `last request: the robot ${lastRequest.text}: ${lastRequest.outcome_text}` : '');
    HMI.text('task', v.task ? v.task.text : 'no task state yet');
    const queue = v.queue || {};
    HMI.text('queue', queue.waiting === undefined || queue.waiting === null
      ? 'no report from the task manager yet'
      : `${queue.waiting} waiting; ${queue.completed} done`
        + (queue.waiting_for && queue.waiting_for !== 'none' ? `; waiting for ${queue.waiting_for}` : ''));
    if (changed('orders', v.orders)) {
      const orders = document.getElementById('orders');
      orders.replaceChildren();
      for (const order of v.orders || []) {
        const li = item(orders, 'li', `${order.words}, from ${order.from}: ${order.text}`);
        li.title = `the model's task (tp, tc, tx): (${order.task.join(', ')})`;
      }
    }
    if (changed('history', v.history)) {
      const body = document.querySelector('#history tbody');
      body.replaceChildren();
      for (const t of v.history || []) {
        const row = item(body, 'tr', '');
        row.title = `the model's task (tp, tc, tx): (${t.task.join(', ')})`;
        for (const cell of [t.number, t.words, t.seen_epoch,
                            t.commit_epoch === null ? '-' : t.commit_epoch,
                            t.commit_epoch === null ? '-' : t.committed,
                            t.done_epoch === null ? '-' : t.done_epoch]) {
          item(row, 'td', String(cell));
        }
      }
    }
    if (changed('belief', v.belief)) bars(v.belief);
    const fail = document.getElementById('fail-safe');
    const fs = v.fail_safe;
    fail.dataset.level = fs ? fs.level : 'none';
    fail.title = fs && fs.reasons.length ? fs.reasons.join('; ') : '';
    HMI.text('fail-safe', fs ? fs.text : 'no report from the decision node yet');
    const robot = v.robot;
    const arm = document.getElementById('robot');
    arm.dataset.stopped = robot && robot.stopped ? 'true' : 'false';
    HMI.text('robot', !robot ? 'the robot side is not running' : [
      robot.stopped ? `protective stop${robot.stop_reason ? `: ${robot.stop_reason}` : ''}` : null,
      robot.separation !== undefined
        ? `the worker is ${robot.separation.toFixed(2)} m from the arm (it needs ${robot.protective_distance.toFixed(2)} m at its speed)` : null,
      robot.speed_override !== undefined ? `speed ${Math.round(100 * robot.speed_override)}%` : null,
    ].filter(Boolean).join('; '));
    if (v.limits) {
      for (const name of ['priority', 'duration']) {
        const [low, high] = v.limits[name];
        const hint = name === 'priority' ? `a whole number from ${low} to ${high}`
          : `a whole number of steps from ${low} to ${high} (a step is one decision of the robot`
            + (v.limits.step_s ? `, ${v.limits.step_s} s here)` : ')');
        HMI.text(`${name}-hint`, hint);
      }
    }
    if (changed('figures', v.figures)) figures(v.figures);
    if (v.words && changed('words', v.words)) CONSOLE.words(v.words);
  }

  function showResult(status, words) {
    result.dataset.status = status;
    result.textContent = words;
  }

  const link = HMI.connect('operator', {
    view: render,
    feed: CONSOLE.feed,
    reply(message) {
      if (message.type === 'order_result') {
        if (message.ref === sent || message.ref === null) showResult(message.status, message.text);
      } else if (message.type === 'error') {
        showResult('refused', message.text);
      }
    },
  });

  windowSelect.addEventListener('change', () => figures(last && last.figures));

  form.addEventListener('submit', (event) => {
    event.preventDefault();
    const fields = {};
    for (const name of ['priority', 'duration', 'nature']) {
      const value = form.elements[name].value.trim();
      fields[name] = /^[0-9]+$/.test(value) ? Number(value) : value;
    }
    sent += 1;
    if (link.send({type: 'order', ref: sent, ...fields})) {
      showResult('checking', 'sending...');
    } else {
      showResult('refused', 'no connection to the cell: nothing sent');
    }
  });
})();
