// The API client: fetch with the bearer key, RFC 9457 problems as errors, SSE subscriptions.
//
// A 401 asks for the key once (the prompt is installed by app.js), keeps it in sessionStorage
// and retries. EventSource and <img>/<a> cannot send headers: their URLs carry ?token=, a
// short-lived read token of that one job (every job document the API returns has one); the key
// itself never goes into a URL.

import { FINISHED } from "./statuses.js";   // served by the API from schemas.records.FINISHED

export { FINISHED };

const STORAGE = "ndrf.apiKey";
let prompt = async () => { throw new Error("no API key prompt installed"); };
let asking = null;                       // one prompt at a time, shared by concurrent requests

export function setKeyPrompt(fn) { prompt = fn; }
export function apiKey() { return sessionStorage.getItem(STORAGE) || ""; }
export function forgetKey() { sessionStorage.removeItem(STORAGE); }

function obtainKey(rejected) {
  asking ??= prompt(rejected)
    .then((key) => { sessionStorage.setItem(STORAGE, key); return key; })
    .finally(() => { asking = null; });
  return asking;
}

/** A non-2xx answer; `problem` is the problem+json body (or a stand-in), `errors` its field list. */
export class ApiError extends Error {
  constructor(status, problem) {
    super(problem.detail || problem.title || `HTTP ${status}`);
    this.status = status;
    this.problem = problem;
    this.errors = Array.isArray(problem.errors) ? problem.errors : [];
  }
}

async function readProblem(response) {
  try {
    const body = await response.json();
    if (body && typeof body === "object") return body;
  } catch { /* not JSON */ }
  return { title: response.statusText || "Error", status: response.status };
}

/** fetch() a path of the API with the key; retries after asking for a key on 401. */
export async function request(path, { method = "GET", body, headers = {}, signal } = {}) {
  for (;;) {
    const used = apiKey();
    const head = { Accept: "application/json", ...headers };
    if (used) head.Authorization = `Bearer ${used}`;
    if (body !== undefined) head["Content-Type"] = "application/json";
    const response = await fetch(path, {
      method, headers: head, signal, body: body === undefined ? undefined : JSON.stringify(body),
    });
    if (response.status === 401) {
      if (apiKey() === used) await obtainKey(Boolean(used));   // else: a new key arrived meanwhile
      continue;
    }
    if (!response.ok) throw new ApiError(response.status, await readProblem(response));
    return response;
  }
}

const readTokens = new Map();             // job id -> its latest read token

function remember(document) {
  for (const job of [document, ...(Array.isArray(document?.items) ? document.items : [])]) {
    if (job && typeof job.id === "string" && job.read_token) readTokens.set(job.id, job.read_token);
  }
  return document;
}

export async function getJSON(path, options) {
  return remember(await (await request(path, options)).json());
}

export async function postJSON(path, body, options = {}) {
  return remember(await (await request(path, { ...options, method: "POST", body })).json());
}

/** A URL for <img>, <a> and EventSource under /v1/jobs/<id>/: it carries ?token= with that job's
 * read token (fetch the job first; without API keys there is no token and none is needed). */
export function authUrl(path) {
  const match = /^\/v1\/jobs\/([0-9a-f]{20})(\/|$|\?)/.exec(path);
  const token = match && readTokens.get(match[1]);
  if (!token) return path;
  return `${path}${path.includes("?") ? "&" : "?"}token=${encodeURIComponent(token)}`;
}

/**
 * Follow a job's event stream from event `after`. `handlers` maps event types to functions of
 * the parsed data; `onState` hears "live", "reconnecting" and "closed". The browser reconnects
 * by itself with Last-Event-ID; a refused stream (401, 404) ends as "closed".
 * Returns { close() }.
 */
export function subscribe(jobId, after, handlers, onState = () => {}) {
  const source = new EventSource(authUrl(`/v1/jobs/${encodeURIComponent(jobId)}/events?after=${after}`));
  for (const [type, handle] of Object.entries(handlers)) {
    source.addEventListener(type, (message) => handle(JSON.parse(message.data), Number(message.lastEventId)));
  }
  source.onopen = () => onState("live");
  source.onerror = () => onState(source.readyState === EventSource.CLOSED ? "closed" : "reconnecting");
  return { close: () => source.close() };
}
