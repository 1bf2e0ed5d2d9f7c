// The self-hosted Swagger UI shell: every request, the spec's included, carries the
// token the status page signed in with (sessionStorage of this tab) through requestInterceptor.
"use strict";
const TOKEN_KEY = "oarmreg.token";
document.addEventListener("DOMContentLoaded", () => {
  const m = /^#token=([^&]+)/.exec(location.hash);
  if (m) {
    sessionStorage.setItem(TOKEN_KEY, decodeURIComponent(m[1]));
    history.replaceState(null, "", location.pathname + location.search);
  }
  if (!sessionStorage.getItem(TOKEN_KEY)) { document.getElementById("docs-sign-in").hidden = false; return; }
  window.ui = SwaggerUIBundle({
    url: "/openapi.json",
    dom_id: "#swagger-ui",
    deepLinking: false,
    validatorUrl: null,  // never ask a validator on another origin
    requestInterceptor: (req) => {
      const token = sessionStorage.getItem(TOKEN_KEY);
      if (token) req.headers.Authorization = "Bearer " + token;
      return req;
    },
  });
});
