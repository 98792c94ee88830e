// The page's sign-in (relay/guard/signin.py): a form while the relay asks for a credential, and a
// one-click sign-out once signed in. The credential becomes an HttpOnly session cookie: it never
// enters the page's address, and the page never reads it back.

const $ = (sel) => document.querySelector(sel);
const ASK_TRIES = 5; // asks of GET /signin before the page starts its feed all the same
const ASK_TIMEOUT_MS = 5000; // an ask with no answer by then is asked again
const ASK_RETRY_MS = 1000;

/** Whether the page may read the relay's data; shows the form when it must sign in first. An ask
 * left without an answer is given up after ASK_TIMEOUT_MS and asked again: awaited for ever, the
 * page would show neither the form nor a feed. */
export async function signedIn() {
  let who;
  for (let ask = 1; who === undefined; ask++) {
    try {
      const r = await fetch("/signin", { cache: "no-store", signal: AbortSignal.timeout(ASK_TIMEOUT_MS) });
      who = await r.json();
    } catch (_) {
      if (ask === ASK_TRIES) return true; // the relay is unreachable: the feed says so and retries
      await new Promise((resolve) => setTimeout(resolve, ASK_RETRY_MS));
    }
  }
  if (who.principal) {
    const out = $("#signout");
    out.hidden = false;
    out.title = `signed in as ${who.principal.name} (${who.principal.role}): sign out`;
  }
  if (who.required && !who.principal) {
    showSignIn(null);
    return false;
  }
  return true;
}

/** Show the sign-in form, saying why when the relay refused the page (an expired session). */
export function showSignIn(reason) {
  $("#signin").hidden = false;
  $("#conn").className = "conn conn-wait";
  $("#conn").textContent = "signed out";
  $("#signin-error").textContent = reason || "";
  $("#signin-token").focus();
}

$("#signin").addEventListener("submit", async (event) => {
  event.preventDefault();
  const body = new URLSearchParams({ token: $("#signin-token").value });
  let message;
  try {
    const r = await fetch("/signin", { method: "POST", body });
    if (r.ok) {
      location.reload(); // the same address, now with the cookie: everything starts signed in
      return;
    }
    message = `${r.status} ${r.statusText}`;
    message = (await r.json()).error ?? message;
  } catch (err) {
    message = message || String(err);
  }
  $("#signin-error").textContent = message;
});

$("#signout").addEventListener("click", async () => {
  await fetch("/signout", { method: "POST" });
  location.reload();
});
