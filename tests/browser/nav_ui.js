// A navigation UI served from a second origin (tests/browser/test_page.py): calls the oarmreg API
// cross-origin, first without the token (must be refused, readably), then with it (a CORS
// pre-flight for the Authorization header, then the real request).
"use strict";
(async () => {
  const api = new URLSearchParams(location.search).get("api");
  const token = location.hash.slice(1);
  const anon = await fetch(api + "/status");
  const r = await fetch(api + "/registration/current", { headers: { Authorization: "Bearer " + token } });
  const result = { anonymous_status: anon.status, status: r.status, body: await r.json() };
  document.body.dataset.result = JSON.stringify(result);
})().catch((e) => { document.body.dataset.error = String(e); });
