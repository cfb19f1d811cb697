// What both engine pages do the same way: read back one light's shadow term as visibility, pack
// float arrays for the DevTools pipe, and publish the page's entry points (shadowlab.techniques.engines).

// a Float32Array as base64 (the pipe carries text)
export function b64(f32) {
  const u8 = new Uint8Array(f32.buffer, f32.byteOffset, f32.byteLength);
  let s = '';
  for (let i = 0; i < u8.length; i += 0x8000) s += String.fromCharCode.apply(null, u8.subarray(i, i + 0x8000));
  return btoa(s);
}

// one light's result from its RGBA float frames with and without shadows received: visibility is
// their ratio (exactly the factor the engine multiplies the light by; 1 where the light does not
// reach), `above_one` counts ratios above 1 (the engine added light); the unshadowed light (RGB)
// is sent once per light and page (`sent` remembers)
export function lightItem(name, lit, shadowed, n, sent) {
  const v = new Float32Array(n);
  let bad = 0;
  for (let k = 0; k < n; k++) {
    const u = lit[4 * k] + lit[4 * k + 1] + lit[4 * k + 2];
    const s = shadowed[4 * k] + shadowed[4 * k + 1] + shadowed[4 * k + 2];
    if (!(u > 1e-7)) { v[k] = 1.0; continue; }
    const r = s / u;
    if (r > 1.0 + 1e-4) bad++;
    v[k] = Math.min(1.0, Math.max(0.0, r));
  }
  const item = { name, vis: b64(v), above_one: bad };
  if (!sent.has(name)) {
    const rgb = new Float32Array(3 * n);
    for (let k = 0; k < n; k++) { rgb[3 * k] = lit[4 * k]; rgb[3 * k + 1] = lit[4 * k + 1]; rgb[3 * k + 2] = lit[4 * k + 2]; }
    item.lit = b64(rgb);
    sent.add(name);
  }
  return item;
}

// a rejected promise's value shown as text (Runtime.evaluate reports a bare rejection without it)
const said = (f) => async (arg) => {
  try { return await f(arg); } catch (e) { throw new Error((e && (e.stack || e.message)) || String(e)); }
};

// the page's entry points, which engines.Session polls for (`ready`) and calls
export function publish(load, render, S) {
  window.shadowlab = { load: said(load), render: said(render), ready: true, S };
}
