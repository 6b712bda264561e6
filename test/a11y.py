"""Accessibility checks run inside a page (Playwright's `page.evaluate`), for the HMI's browser
tests: the WCAG 2.1 AA contrast of every text the page shows, and the focus indicator of an
element (test/test_hmi_console.py).

Contrast: every visible element with text of its own (a text node child), and every input,
select and button, against the colour behind it: the element's and its ancestors' background
colours composited from the page up (each may be translucent); text colour with alpha
composited over that. Large text (24 px, or 18.66 px bold) needs 3:1, the rest 4.5:1 (WCAG 1.4.3).
No page here draws text over an image, so background colours are all there is behind text.
"""

CONTRAST = r"""() => {
  const parse = (c) => {
    const m = c.match(/rgba?\(([^)]+)\)/);
    if (!m) return [0, 0, 0, 0];
    const v = m[1].split(/[ ,/]+/).filter(Boolean).map(Number);
    return [v[0], v[1], v[2], v.length > 3 ? v[3] : 1];
  };
  const over = (top, bottom) => {              // composite top over an opaque bottom
    const a = top[3];
    return [0, 1, 2].map((i) => top[i] * a + bottom[i] * (1 - a)).concat([1]);
  };
  const lum = (c) => {
    const [r, g, b] = c.slice(0, 3).map((v) => {
      v /= 255;
      return v <= 0.04045 ? v / 12.92 : ((v + 0.055) / 1.055) ** 2.4;
    });
    return 0.2126 * r + 0.7152 * g + 0.0722 * b;
  };
  const ratio = (a, b) => {
    const [x, y] = [lum(a), lum(b)].sort((p, q) => q - p);
    return (x + 0.05) / (y + 0.05);
  };
  const behind = (element) => {
    const layers = [];
    for (let e = element; e; e = e.parentElement) {
      const c = parse(getComputedStyle(e).backgroundColor);
      if (c[3] > 0) layers.push(c);
    }
    let colour = [255, 255, 255, 1];          // the canvas
    for (const layer of layers.reverse()) colour = over(layer, colour);
    return colour;
  };
  const failures = [];
  let checked = 0;
  for (const element of document.querySelectorAll('body *')) {
    const own = [...element.childNodes].some((n) => n.nodeType === 3 && n.textContent.trim());
    const control = ['INPUT', 'SELECT', 'BUTTON'].includes(element.tagName);
    if (!own && !control) continue;
    if (element.closest('[hidden]') || element.tagName === 'OPTION') continue;
    const box = element.getBoundingClientRect();
    const style = getComputedStyle(element);
    if (!box.width || !box.height || style.visibility !== 'visible'
        || !element.checkVisibility({opacityProperty: true})) continue;
    const background = behind(element);
    const colour = over(parse(style.color), background);
    const size = parseFloat(style.fontSize);
    const large = size >= 24 || (size >= 18.66 && Number(style.fontWeight) >= 700);
    const needed = large ? 3 : 4.5;
    const r = ratio(colour, background);
    checked += 1;
    if (r < needed) {
      failures.push(`${element.tagName.toLowerCase()}${element.id ? '#' + element.id : ''}`
        + ` "${(element.textContent || element.value || '').trim().slice(0, 40)}":`
        + ` ${r.toFixed(2)} < ${needed} (${style.color} on`
        + ` rgb(${background.slice(0, 3).map(Math.round)}))`);
    }
  }
  return {checked, failures};
}"""

# The focused element's indicator: the outline (width, colour against the page behind the
# element) and the inset ring inside it (width, colour against the element's own background)
FOCUS = r"""() => {
  const element = document.activeElement;
  const style = getComputedStyle(element);
  const parent = element.parentElement;
  let page = 'rgb(255, 255, 255)';
  for (let e = parent; e; e = e.parentElement) {
    const c = getComputedStyle(e).backgroundColor;
    if (!/rgba\(0, 0, 0, 0\)|transparent/.test(c)) { page = c; break; }
  }
  const shadow = style.boxShadow.match(/(rgba?\([^)]+\)) 0px 0px 0px (\d+(?:\.\d+)?)px inset/);
  return {id: element.id, tag: element.tagName, focusVisible: element.matches(':focus-visible'),
          outlineStyle: style.outlineStyle, outlineWidth: parseFloat(style.outlineWidth),
          outlineColor: style.outlineColor, outlineOffset: parseFloat(style.outlineOffset),
          ringColor: shadow ? shadow[1] : null, ringWidth: shadow ? parseFloat(shadow[2]) : 0,
          background: style.backgroundColor, page};
}"""


def rgb(colour: str) -> tuple[float, float, float]:
    inner = colour[colour.index('(') + 1:colour.index(')')].replace('/', ' ').replace(',', ' ')
    r, g, b = (float(v) for v in inner.split()[:3])
    return r, g, b


def luminance(colour: str) -> float:
    def channel(v):
        v /= 255
        return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4
    r, g, b = (channel(v) for v in rgb(colour))
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def contrast(a: str, b: str) -> float:
    x, y = sorted((luminance(a), luminance(b)), reverse=True)
    return (x + 0.05) / (y + 0.05)
