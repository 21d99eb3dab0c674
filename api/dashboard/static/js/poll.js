// The dashboard's one poll loop: the jobs and experiments lists, the usage strip and an
// experiment's page re-read the API with it.

/**
 * Call `step` now, then again `ms` after each call has settled.
 *
 * - `step` returns false to pause the loop (what it follows has finished); `now()` starts it again.
 * - A throwing `step` goes to `onError`; the loop goes on unless `onError` returns false (the
 *   default logs the error).
 * - `hidden`: whether to call `step` while the tab is hidden (default false: the loop only waits).
 * - `now()` calls `step` at once (after a change the page made itself) and restarts the wait.
 * - `stop()` ends the loop for good (the view is left); a call in flight schedules nothing.
 *
 * Returns { now(), stop() }.
 */
export function poll(step, ms, { onError = (error) => console.warn(error), hidden = false } = {}) {
  let timer = null, stopped = false;

  async function run() {
    clearTimeout(timer);
    if (stopped) return;
    let again = true;
    if (hidden || !document.hidden) {
      try {
        again = (await step()) !== false;
      } catch (error) {
        again = stopped || onError(error) !== false;
      }
    }
    clearTimeout(timer);                  // one pending call, also when calls overlapped
    if (again && !stopped) timer = setTimeout(run, ms);
  }

  run();
  return {
    now: () => run(),
    stop: () => { stopped = true; clearTimeout(timer); },
  };
}
