//! The one integration-test binary: the real app on a random port with a fresh database.
//!
//! - `openapi`: `openapi.yaml` against the served operations; every response received by these
//!   tests is checked against the document.
//! - `deploy`: `compose.yaml` and the load balancer's config (and `docker compose config` where installed), and the
//!   Kubernetes manifests rendered by `kubectl kustomize` and checked by `kubernetes-validate`.
//! - `hostile`: half-open and idle connections, stalled bodies, admission before the body, head
//!   limits, keys on the operational routes, the audit log (raw TCP where needed).
//! - `http`: the HTTP layer (formats, every bad-input class, limits, keys, timeouts, overload,
//!   storage) with a stand-in face engine.
//! - `pipeline`: enrol and verify real IMM photos through the real `Pipeline` and committed models;
//!   analyse, avatar and frontal rendering, byte for byte the CLI's.
//! - `replicas`: two `facegate serve` processes on one PostgreSQL database agree at once.
//! - `postgres`: a real PostgreSQL server (a throwaway cluster, or `FACEGATE_TEST_POSTGRES`).
//! - `store_backends`: the template store on SQLite and PostgreSQL through one test body each; concurrent
//!   migration and the change feed on PostgreSQL.
//! - `fail_closed`: `facegate serve` refuses to start on an API-key setting with no key and on a sealed
//!   database without the key that opens it; what a DELETE erases (`Facegate-Erasure`), and a backup
//!   from before it restored with the same key.
//! - `secrets`: a failed start-up (`serve` in both log formats, the store commands) prints no
//!   database password, given in the URL or by `--database-password-file`.
//! - `store_cli`: `facegate rekey`, `backup` and `restore`, the real binary on a real database.
//! - `liveness`: `--liveness enforce`, `report` and `off` and an operator's threshold, through the
//!   real pipeline and `models/liveness.bin` on NUAA print and live frames.
//! - `frames`: `/verify` of a capture (a probe and further frames): the frames' checks (a face,
//!   the probe's person), the liveness fused over them, enforced by the fused score; NUAA frames.
//! - `challenge`: the head-turn liveness challenge: issued, answered by a person's own turns,
//!   used once, expired; a still photo and the wrong order fail it; JSON and multipart.
//! - `challenge_limits`: the rate per address and the cap on open challenges (429
//!   `too-many-challenges` with `Retry-After`), and the bounded sweep of expired ones.
//! - `store_vanished`: a SQLite file unlinked or emptied under the service: `/health` 503 within
//!   2 s, enrolments refused 503; a file that is not a database is 503, not 500.
//! - `telemetry`: OpenTelemetry traces of the real binary to an OTLP/HTTP receiver started by the
//!   test: a `/verify`'s `traceparent` continued, its stages' spans.
//! - `browser`: the web console in headless Chromium over WebDriver, against the real pipeline.

mod admission;
mod browser;
mod challenge;
mod challenge_limits;
mod deploy;
mod fail_closed;
mod frames;
mod hostile;
mod http;
mod json_bounds;
mod liveness;
mod liveness_calibration;
mod openapi;
mod pipeline;
mod postgres;
mod protection;
mod recognizers;
mod replicas;
mod secrets;
mod site_calibration;
mod store_backends;
mod store_cli;
mod store_outage;
mod store_vanished;
mod support;
mod telemetry;
