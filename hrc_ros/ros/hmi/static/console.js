// The operator's console: the timeline of the last 10 minutes (uPlot, vendor/) and the event
// log, both fed by the server's feeds (a reset with what it holds, then what is new).
'use strict';
const CONSOLE = (() => {
  const SPAN = 600;                 // seconds the timeline shows
  const EVENTS_KEPT = 200;
  const ACTIONS = ['nw', 'rh1', 'rh2', 'ct', 'dp', 'dm', 'mh', 'dn'];
  const ACTION_COLOURS = {nw: '#8a8a8a', rh1: '#1f77b4', rh2: '#17becf', ct: '#2ca02c',
                          dp: '#ff7f0e', dm: '#8c564b', mh: '#e377c2', dn: '#d62728'};
  const LEVELS = ['low', 'medium', 'high'];
  const STOP_FILL = 'rgba(179, 38, 30, 0.18)';
  let names = {};                   // action -> words (from the view)
  const epochs = {t: [], k: [], action: [], motivation: [], aggression: [], d: []};
  const robot = {t: [], S: [], Sp: [], override: []};
  let stops = [];                   // [t, 1 | 0], in time order
  let events = [];                  // newest first
  let charts = null, drawing = false;
  const box = document.getElementById('timeline');

  function clear(series) { for (const key of Object.keys(series)) series[key].length = 0; }

  function newest() {
    return Math.max(epochs.t.length ? epochs.t[epochs.t.length - 1] : 0,
                    robot.t.length ? robot.t[robot.t.length - 1] : 0,
                    stops.length ? stops[stops.length - 1][0] : 0);
  }

  function trim() {
    const oldest = newest() - SPAN;
    for (const series of [epochs, robot]) {
      let n = 0;
      while (n < series.t.length && series.t[n] < oldest) n += 1;
      if (n) for (const key of Object.keys(series)) series[key].splice(0, n);
    }
    // keep the last edge before the window: a stop that began earlier still shows
    let n = 0;
    while (n + 1 < stops.length && stops[n + 1][0] < oldest) n += 1;
    if (n) stops.splice(0, n);
  }

  function take(rows) {
    for (const [t, k, action, motivation, aggression, d] of rows.epochs || []) {
      epochs.t.push(t); epochs.k.push(k); epochs.action.push(ACTIONS.indexOf(action));
      epochs.motivation.push(motivation); epochs.aggression.push(aggression); epochs.d.push(d);
    }
    for (const [t, S, Sp, override] of rows.robot || []) {
      robot.t.push(t); robot.S.push(S); robot.Sp.push(Sp);
      robot.override.push(override === null ? null : 100 * override);
    }
    for (const edge of rows.stops || []) stops.push(edge);
  }

  // -- the charts ----------------------------------------------------------------------------
  function range() {
    const end = newest();
    return [end - SPAN, end];
  }

  function stopSpans(x0, x1) {
    // [start, end] of each stop in the window; one that began before the window (its edge
    // trimmed away, or the first edge an end) starts at x0, one going on ends at x1
    const spans = [];
    let start = null;
    stops.forEach(([t, on], i) => {
      if (on && start === null) start = Math.max(t, x0);
      else if (!on && start !== null) { spans.push([start, t]); start = null; }
      else if (!on && i === 0 && t > x0) spans.push([x0, t]);
    });
    if (start !== null) spans.push([start, x1]);
    return spans.filter(([a, b]) => b > x0);
  }

  function shadeStops(u) {
    const [x0, x1] = range();
    const {ctx} = u;
    ctx.save();
    ctx.fillStyle = STOP_FILL;
    for (const [a, b] of stopSpans(x0, x1)) {
      const left = u.valToPos(a, 'x', true), right = u.valToPos(b, 'x', true);
      ctx.fillRect(left, u.bbox.top, Math.max(2, right - left), u.bbox.height);
    }
    ctx.restore();
  }

  function strip(u) {
    const {ctx} = u;
    const t = epochs.t;
    ctx.save();
    for (let i = 0; i < t.length; i += 1) {
      const end = i + 1 < t.length ? t[i + 1] : t[i] + (i > 0 ? t[i] - t[i - 1] : 1);
      const left = u.valToPos(t[i], 'x', true), right = u.valToPos(end, 'x', true);
      ctx.fillStyle = ACTION_COLOURS[ACTIONS[epochs.action[i]]] || '#000';
      ctx.fillRect(left, u.bbox.top, Math.max(1, right - left - 1), u.bbox.height);
    }
    ctx.restore();
  }

  const AXIS = {stroke: '#333', grid: {stroke: '#e3e3e0', width: 1},
                ticks: {stroke: '#c8c8c4', width: 1}};

  function chart(element, height, series, axes, hooks) {
    return new uPlot({
      width: Math.max(280, box.clientWidth - 8), height,
      scales: {x: {time: true, range: () => range()}, ...axes.scales},
      series: [{label: 'time'}, ...series],
      axes: [{...AXIS}, ...axes.list],
      cursor: {sync: {key: 'hrc-console'}, drag: {x: false, y: false}},
      legend: {live: true},
      hooks: {draw: hooks},
    }, null, element);
  }

  function create() {
    box.replaceChildren();
    const holder = (label) => {
      const element = document.createElement('div');
      element.className = 'chart';
      element.dataset.chart = label;
      box.appendChild(element);
      return element;
    };
    const levels = (u, values) => values.map((v) => LEVELS[v] || '');
    const worker = chart(holder('worker'), 170, [
      {label: 'motivation', stroke: '#1f6f8b', width: 2, scale: 'level',
       value: (u, v) => (v === null ? '-' : v.toFixed(2))},
      {label: 'aggression', stroke: '#b3261e', width: 2, scale: 'level',
       value: (u, v) => (v === null ? '-' : v.toFixed(2))},
      {label: 'distance level', stroke: '#6b4fa0', width: 2, dash: [6, 4], scale: 'd',
       paths: uPlot.paths.stepped({align: 1}), value: (u, v) => (v === null ? '-' : String(v))},
    ], {scales: {level: {range: [0, 2]}, d: {range: [0, 3]}},
        list: [{...AXIS, scale: 'level', values: levels, splits: [0, 1, 2], size: 64,
                label: 'belief, mean level'},
               {...AXIS, scale: 'd', side: 1, splits: [0, 1, 2, 3], grid: {show: false},
                label: 'distance level', size: 50}]},
    [shadeStops]);
    const arm = chart(holder('arm'), 170, [
      {label: 'separation (m)', stroke: '#111111', width: 2, scale: 'm',
       value: (u, v) => (v === null ? '-' : v.toFixed(2))},
      {label: 'needed at its speed (m)', stroke: '#b3261e', width: 2, dash: [6, 4], scale: 'm',
       value: (u, v) => (v === null ? '-' : v.toFixed(2))},
      {label: 'speed (%)', stroke: '#1d7a36', width: 1.5, scale: '%',
       value: (u, v) => (v === null ? '-' : `${Math.round(v)}%`)},
    ], {scales: {m: {range: (u, min, max) => [0, Math.max(1, max || 1)]}, '%': {range: [0, 100]}},
        list: [{...AXIS, scale: 'm', label: 'separation, m', size: 64},
               {...AXIS, scale: '%', side: 1, grid: {show: false}, label: 'speed %', size: 50}]},
    [shadeStops]);
    const actions = chart(holder('actions'), 90, [
      {label: 'the robot', scale: 'strip', paths: () => null, points: {show: false},
       value: (u, v) => (v === null || v === undefined ? '-' : names[ACTIONS[v]] || ACTIONS[v])},
    ], {scales: {strip: {range: [0, 1]}},
        list: [{...AXIS, scale: 'strip', values: () => [], grid: {show: false}, size: 64}]},
    [strip, shadeStops]);
    charts = {worker, arm, actions};
    new ResizeObserver(() => {
      if (!charts) return;
      const width = Math.max(280, box.clientWidth - 8);
      for (const u of Object.values(charts)) if (u.width !== width) u.setSize({width, height: u.height});
    }).observe(box);
  }

  function draw() {
    drawing = false;
    trim();
    if (!charts && epochs.t.length + robot.t.length > 0) create();
    if (!charts) return;
    charts.worker.setData([epochs.t, epochs.motivation, epochs.aggression, epochs.d]);
    charts.arm.setData([robot.t, robot.S, robot.Sp, robot.override]);
    charts.arm.root.hidden = robot.t.length === 0;
    charts.actions.setData([epochs.t, epochs.action]);
    const spans = stopSpans(...range()).length;
    box.dataset.epochs = String(epochs.t.length);
    box.dataset.robot = String(robot.t.length);
    box.dataset.stops = String(spans);
    const closest = robot.S.length ? Math.min(...robot.S) : null;
    box.setAttribute('aria-label', `the last 10 minutes: ${epochs.t.length} decisions, `
      + `${spans} protective stop${spans === 1 ? '' : 's'}`
      + (closest === null ? ', the robot side not running'
        : `, the worker came within ${closest.toFixed(2)} m of the arm`));
  }

  function redraw() {
    if (!drawing) { drawing = true; requestAnimationFrame(draw); }
  }

  // -- the event log ----------------------------------------------------------------------
  function clock(ms) {
    return new Date(ms).toLocaleTimeString([], {hour: '2-digit', minute: '2-digit', second: '2-digit'});
  }

  function entry(event) {
    const li = document.createElement('li');
    li.dataset.kind = event.kind;
    const time = document.createElement('time');
    time.dateTime = new Date(event.t_ms).toISOString();
    time.textContent = clock(event.t_ms);
    const kind = document.createElement('span');
    kind.className = 'kind';
    kind.textContent = event.kind;
    const words = document.createElement('span');
    words.className = 'text';
    words.textContent = event.text;
    li.append(time, ' ', kind, ' ', words);
    if (event.detail) li.title = event.detail;
    return li;
  }

  function logEvents(items, reset) {
    const list = document.getElementById('events');
    if (reset) { events = []; list.replaceChildren(); }
    for (const event of items) {
      events.unshift(event);
      list.insertBefore(entry(event), list.firstChild);
    }
    events.length = Math.min(events.length, EVENTS_KEPT);
    while (list.children.length > EVENTS_KEPT) list.lastChild.remove();
    list.dataset.count = String(events.length);
  }

  function cell(value) {
    let text = String(value === undefined || value === null ? '' : value);
    if (/^[=+\-@\t\r]/.test(text)) text = `'${text}`;      // not a formula in a spreadsheet
    return /[",\n\r]/.test(text) ? `"${text.replace(/"/g, '""')}"` : text;
  }

  function csv() {
    const lines = ['time,kind,what happened,detail'];
    for (const event of [...events].reverse()) {
      lines.push([new Date(event.t_ms).toISOString(), event.kind, event.text, event.detail]
        .map(cell).join(','));
    }
    const blob = new Blob([`${lines.join('\r\n')}\r\n`], {type: 'text/csv;charset=utf-8'});
    const link = document.createElement('a');
    link.href = URL.createObjectURL(blob);
    const stamp = new Date().toISOString().slice(0, 19).replace(/[-:]/g, '').replace('T', '-');
    link.download = `cell-events-${stamp}.csv`;
    document.body.appendChild(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 10000);
  }
  document.getElementById('events-csv').addEventListener('click', csv);

  function legend() {
    const list = document.getElementById('action-legend');
    list.replaceChildren();
    for (const action of ACTIONS) {
      const li = document.createElement('li');
      const swatch = document.createElement('span');
      swatch.className = 'swatch';
      swatch.style.background = ACTION_COLOURS[action];
      swatch.setAttribute('aria-hidden', 'true');
      li.append(swatch, ` the robot ${names[action] || action}`);
      li.title = `the model's action: ${action}`;
      list.appendChild(li);
    }
  }

  return {
    feed(message) {
      if (message.name === 'timeline') {
        if (message.reset) { clear(epochs); clear(robot); stops = []; }
        for (const rows of message.items) take(rows);
        redraw();
      } else if (message.name === 'events') {
        logEvents(message.items, message.reset);
      }
    },
    words(words) {
      if (JSON.stringify(words.actions) !== JSON.stringify(names)) {
        names = words.actions;
        legend();
      }
    },
  };
})();
