// The job's token travels as the job's files ask for it: an Authorization
// header. It is never put in a URL the server sees: a token given in the
// page's fragment (#token=...) is kept for this tab and the fragment wiped.

const KEY = 'seamstress.token';

/** Reads #token=... once, then removes it from the address bar. */
export function takeFragmentToken() {
  const params = new URLSearchParams(location.hash.slice(1));
  const token = params.get('token');
  if (token) {
    sessionStorage.setItem(KEY, token);
    params.delete('token');
    const rest = params.toString();
    history.replaceState(null, '', location.pathname + location.search + (rest ? '#' + rest : ''));
  }
  return params;
}

function headers() {
  const token = sessionStorage.getItem(KEY);
  return token ? { Authorization: 'Bearer ' + token } : {};
}

/** Asks for a token in a small form; resolves once one is given. */
function askToken(message) {
  return new Promise((resolve) => {
    const form = document.createElement('form');
    form.className = 'token';
    form.innerHTML = '<p></p><input type="password" autocomplete="off" placeholder="token"> <button>Use</button>';
    form.querySelector('p').textContent = message;
    form.onsubmit = (e) => {
      e.preventDefault();
      sessionStorage.setItem(KEY, form.querySelector('input').value.trim());
      form.remove();
      resolve();
    };
    document.body.prepend(form);
  });
}

/** fetch() with the token; asks for one on a 401 and tries again. */
export async function authFetch(url) {
  for (;;) {
    const resp = await fetch(url, { headers: headers(), cache: 'no-store' });
    if (resp.status !== 401) return resp;
    let message = 'This server needs a token.';
    try { message = (await resp.json()).error.message || message; } catch (_) { /* keep the default */ }
    await askToken(message);
  }
}

/** The JSON of a URL, or an error naming the status. */
export async function getJson(url) {
  const resp = await authFetch(url);
  if (!resp.ok) throw new Error(`${url}: ${resp.status} ${await resp.text()}`);
  return resp.json();
}
