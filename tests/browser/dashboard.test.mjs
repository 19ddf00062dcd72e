// Browser tests of the dashboard: headless Chromium (Debian's `chromium`, driven by
// playwright-core) against the real `safedice serve` binary on a free loopback port with a
// fresh data dir. The tests run in order and share one server: upload, submit, watch, chart,
// act, compare. Run: `npm ci && npm test` here, after `cargo build` (see README, Dashboard).
//
// Environment: SAFEDICE_BIN (default ../../target/debug/safedice), CHROMIUM (default: chromium
// on PATH), SCREENSHOT_DIR (when set, PNGs of the main pages are written there).
//
// The parts run in the order imported below, in one process (their tests share the session
// of session.mjs: later parts use the datasets, job and policy the earlier ones made).

import './session.mjs';
import './datasets_jobs.mjs';
import './models.mjs';
import './experiments_layout.mjs';
