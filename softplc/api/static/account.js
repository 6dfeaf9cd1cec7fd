/* softplc operator page: who acts (docs/web.md, Security). The login form (a session cookie,
   HttpOnly: this page never reads it), log out, the key dialog (a key in sessionStorage, sent
   only in the Authorization header), who is logged in and their role in the header, and a
   refusal (401, 403) said plainly with the way to log in. Loaded after app.js, whose
   `$`, `text`, `say`, `headers`, `API`, `page` and `startStream` it uses; app.js calls
   `askToken`, `denied` and `whoami` from here once the page runs. */
"use strict";

function askToken(reason) {
  const dialog = $("#token-dialog");
  text($("#auth-reason"), reason || "");
  if (!dialog.open) dialog.showModal();
}

$("#token-form").addEventListener("submit", () => {
  sessionStorage.setItem("softplc-token", $("#token").value.trim());
  $("#token").value = "";
  whoami();
  startStream();
});

/* -- who is logged in: the login form, log out, refusals said plainly --------------------- */

page.who = { user: null, role: null, via: "anonymous" };

async function whoami() {
  let who = { user: null, role: null, via: "anonymous" };
  try {
    const response = await fetch(API + "/whoami", { headers: headers() });
    if (response.ok) who = await response.json();  // 401 off loopback: nobody
  } catch (e) { /* no answer: shown as nobody until the next look */ }
  page.who = who;
  const el = $("#who");
  el.replaceChildren();
  const name = document.createElement("b");
  name.textContent = who.user || "not logged in";
  const role = document.createElement("span");
  role.className = "role";
  role.textContent = who.role ? ` ${who.role}${who.user ? "" : " (reads only)"}` : "";
  el.append(name, role);
  el.title = who.user ? `${who.user}, ${who.role}, by ${who.via}` : "";
  $("#login-open").classList.toggle("hidden", Boolean(who.user));
  $("#logout").classList.toggle("hidden", !who.user);
  return who;
}

const article = (role) => (/^[aeiou]/.test(role) ? "an " : "a ") + role;

/* A 401 or 403 in plain words: who is asking, what the action needs, and the way to log in.
   The server's line names the role the route needs ("POST /api/v1/stop needs operator"). */
function denied(what, answer) {
  if (answer.status !== 401 && answer.status !== 403) return false;
  const needs = (answer.data.error || "").match(/needs (\w+)/);
  const who = page.who.user ? `${page.who.user} is ${article(page.who.role)}` : "not logged in";
  say(`${what} refused: ${who}; ${what} needs ${needs ? article(needs[1]) : "more rights"}.`,
      false);
  $("#offer-login").classList.remove("hidden");
  return true;
}

function openLogin() {
  text($("#login-error"), "");
  askToken("");
  $("#login-user").focus();
}

$("#login-open").addEventListener("click", openLogin);
$("#offer-login").addEventListener("click", openLogin);

$("#login-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();  // no navigation (the page's CSP allows no form action anyway)
  const error = $("#login-error");
  text(error, "logging in…");
  let answer;
  try {
    // No Authorization header: /login would take a key's user instead of this one.
    const response = await fetch(API + "/login", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ user: $("#login-user").value.trim(),
                             password: $("#login-password").value }) });
    let data = {};
    try { data = await response.json(); } catch (e) { data = {}; }
    answer = { ok: response.ok, status: response.status, data };
  } catch (e) {
    answer = { ok: false, status: 0, data: { error: "the PLC did not answer" } };
  }
  $("#login-password").value = "";
  if (!answer.ok) { text(error, answer.data.error || `login refused (${answer.status})`); return; }
  text(error, "");
  sessionStorage.removeItem("softplc-token");  // a key would be taken before the session
  $("#token-dialog").close();
  say(`logged in as ${answer.data.user} (${answer.data.role})`, true);
  await whoami();
  startStream();
});

$("#logout").addEventListener("click", async () => {
  sessionStorage.removeItem("softplc-token");
  try { await fetch(API + "/logout", { method: "POST" }); } catch (e) { /* shown below */ }
  const who = await whoami();
  say(who.user ? `still ${who.user}: log out failed` : "logged out", !who.user);
  startStream();
});

whoami();
