// The TypeScript client (types by openapi-typescript, requests by openapi-fetch) against a running
// facegate on a fresh database. Run by tests/clients/run.sh after `tsc`:
// node out/test_typescript.js BASE_URL IMM_DIR. Prints one line per check and closes with
// "typescript: N passed, M failed"; exits non-zero on any failure.
import fs from "node:fs";
import path from "node:path";
import createClient from "openapi-fetch";
import type { components, paths } from "./schema.js";

type Problem = components["schemas"]["Problem"];
type Challenge = components["schemas"]["ChallengeResponse"];
type Turn = components["schemas"]["Turn"];
type Slug = Problem["type"] extends `https://facegate.dev/problems/${infer S}` ? S : never;

const [baseUrl, imm] = process.argv.slice(2) as [string, string];
const client = createClient<paths>({ baseUrl });

const bytes = (name: string) => fs.readFileSync(path.join(imm, name));
const photo = (name: string) => new Blob([bytes(name)], { type: "image/jpeg" });
const b64 = (name: string) => bytes(name).toString("base64");

/** multipart/form-data from a body whose Blob parts go as files (arrays as repeated fields). */
function form(body: unknown): FormData {
  const data = new FormData();
  for (const [name, value] of Object.entries(body as Record<string, string | Blob | Blob[]>)) {
    for (const item of Array.isArray(value) ? value : [value]) {
      if (item instanceof Blob) data.append(name, item, `${name}.jpg`);
      else data.append(name, item);
    }
  }
  return data;
}
const multipart = { bodySerializer: form };

function assert(condition: unknown, message: string): asserts condition {
  if (!condition) throw new Error(message);
}

/** The body of a success, after checking the status. */
function ok<T>(r: { data?: T; error?: unknown; response: Response }, status: number): T {
  assert(r.response.status === status, `status ${r.response.status}, wanted ${status}: ${JSON.stringify(r.error)}`);
  assert(r.data !== undefined, "no body");
  return r.data;
}

/** A problem+json error read as the typed Problem. */
function problem(r: { error?: Problem; response: Response }, status: number, slug: Slug): Problem {
  assert(r.response.status === status, `status ${r.response.status}, wanted ${status}`);
  assert(r.response.headers.get("content-type") === "application/problem+json", `${r.response.headers.get("content-type")}`);
  const p = r.error;
  assert(p !== undefined, "no error body");
  const type: Problem["type"] = `https://facegate.dev/problems/${slug}`;
  assert(p.type === type && p.status === status && p.title && p.detail, JSON.stringify(p));
  return p;
}

// IMM person 15 (enrolled as ts-15 from views 1 and 2): a head-turn challenge step's burst of two
// frames (`frame_steps`) by turn, both frontal views ahead, each turned view twice; and the probe
// looking ahead.
const BURSTS: Record<Turn, string[]> = { left: ["15-4f.jpg", "15-4f.jpg"], right: ["15-3f.jpg", "15-3f.jpg"], front: ["15-5f.jpg", "15-1f.jpg"] };
const CHALLENGE_PROBE = "15-2f.jpg";

async function newChallenge(): Promise<Challenge> {
  const c = ok(await client.POST("/liveness/challenge", {}), 201);
  assert(c.challenge.length > 0 && c.expires_in >= 30 && c.expires_in <= 600, JSON.stringify(c));
  assert(Number.isInteger(c.max_frames_per_step) && c.max_frames_per_step >= 5, JSON.stringify(c));
  const turns = c.steps.map((s) => s.turn);
  assert(turns.length >= 3 && turns.length <= 4 && turns.includes("left") && turns.includes("right"), JSON.stringify(turns));
  for (const s of c.steps) {
    const side = { left: s.yaw_min > 0, right: s.yaw_max < 0, front: s.yaw_min < 0 && s.yaw_max > 0 }[s.turn];
    assert(s.yaw_min < s.yaw_max && side, JSON.stringify(s));
  }
  return c;
}

const checks: Record<string, () => Promise<void>> = {
  async fresh_database() {
    const h = ok(await client.GET("/health"), 200);
    assert(h.status === "ok" && h.subjects === 0 && h.templates === 0, JSON.stringify(h));
  },

  async enrol_by_multipart() {
    const r = await client.POST("/enroll", {
      body: { subject: "ts-01", image: [photo("01-1m.jpg"), photo("01-3m.jpg")] },
      ...multipart,
    });
    const e = ok(r, 201);
    assert(e.subject === "ts-01" && e.added === 2 && e.templates === 2, JSON.stringify(e));
    assert(e.images.every((i) => i.faces_found === 1 && i.landmarks.points.length === 58), "image reports");
    assert(r.response.headers.get("location")?.endsWith("/subjects/ts-01"), "Location");
  },

  async enrol_by_json() {
    let e = ok(await client.POST("/enroll", { body: { subject: "ts-15", images: [b64("15-1f.jpg")] } }), 201);
    assert(e.added === 1 && e.templates === 1, JSON.stringify(e));
    e = ok(await client.POST("/enroll", { body: { subject: "ts-15", image: b64("15-2f.jpg") } }), 201);
    assert(e.added === 1 && e.templates === 2, JSON.stringify(e));
  },

  async verify_match_by_multipart() {
    const v = ok(await client.POST("/verify", { body: { subject: "ts-01", image: photo("01-5m.jpg") }, ...multipart }), 200);
    assert(v.match && v.score >= v.threshold && v.templates_compared === 2 && v.fmr === 0.001, JSON.stringify(v));
    assert(v.pose !== null && Math.abs(v.pose.yaw) < 30, JSON.stringify(v.pose));
  },

  async verify_no_match_by_json_with_fmr() {
    const v = ok(
      await client.POST("/verify", { params: { query: { fmr: 0.01 } }, body: { subject: "ts-01", image: b64("15-4f.jpg") } }),
      200,
    );
    assert(!v.match && v.score < v.threshold && v.fmr !== 0.001, JSON.stringify(v));
  },

  async identify_by_multipart() {
    const i = ok(
      await client.POST("/identify", { params: { query: { k: 2 } }, body: { image: photo("15-5f.jpg") }, ...multipart }),
      200,
    );
    assert(i.subjects_searched === 2 && i.candidates.length === 2, JSON.stringify(i.candidates));
    assert(i.candidates[0]?.subject === "ts-15" && i.candidates[0].match, JSON.stringify(i.candidates));
  },

  async challenge_passed_by_json() {
    // Bursts: two frames a step, `frame_steps` naming each frame's step (0-based).
    const c = await newChallenge();
    const bursts = c.steps.map((s) => BURSTS[s.turn]);
    const names = bursts.flat();
    const frame_steps = bursts.flatMap((burst, i) => burst.map(() => i));
    const body = { subject: "ts-15", image: b64(CHALLENGE_PROBE), challenge: c.challenge, frames: names.map(b64), frame_steps };
    const v = ok(await client.POST("/verify", { body }), 200);
    const outcome = v.liveness?.challenge;
    assert(v.match && outcome !== undefined, JSON.stringify(v.liveness));
    assert(outcome.steps.length === c.steps.length && v.liveness?.frames === names.length + 1, JSON.stringify(v.liveness));
    outcome.steps.forEach((read, i) => {
      const step = c.steps[i];
      assert(step !== undefined && read.turn === step.turn && read.ok, JSON.stringify({ names, step, read }));
      assert(read.yaw !== null && read.yaw >= step.yaw_min && read.yaw <= step.yaw_max, JSON.stringify(read));
      assert(read.frames === 2, JSON.stringify(read));
    });
    assert(outcome.passed && outcome.reason === null && !v.liveness?.attack, JSON.stringify(outcome));
    // Used once: the same challenge again is refused.
    const p = problem(await client.POST("/verify", { body }), 422, "invalid-challenge");
    assert(p.detail.length > 0, JSON.stringify(p));
  },

  async challenge_failed_by_multipart() {
    // Every frame looking ahead, one per step without frame_steps (the contract before bursts):
    // the turned steps are not ok and the challenge fails, saying why.
    const c = await newChallenge();
    const frame = c.steps.map(() => photo("15-1f.jpg"));
    const body = { subject: "ts-15", image: photo(CHALLENGE_PROBE), challenge: c.challenge, frame };
    const v = ok(await client.POST("/verify", { body, ...multipart }), 200);
    const outcome = v.liveness?.challenge;
    assert(outcome !== undefined && outcome.steps.length === c.steps.length, JSON.stringify(v.liveness));
    assert(!outcome.passed && typeof outcome.reason === "string" && outcome.reason.length > 0 && v.liveness?.attack, JSON.stringify(outcome));
    assert(outcome.steps.every((read, i) => read.ok === (c.steps[i]?.turn === "front") && read.frames === 1), JSON.stringify(outcome.steps));
    problem(await client.POST("/verify", { body, ...multipart }), 422, "invalid-challenge");
  },

  async list_subjects_paged() {
    let page = ok(await client.GET("/subjects", { params: { query: { limit: 1 } } }), 200);
    assert(page.subjects.map((s) => s.id).join() === "ts-01" && page.next_after === "ts-01", JSON.stringify(page));
    assert(!Number.isNaN(Date.parse(page.subjects[0]?.created_at ?? "")), "created_at");
    page = ok(await client.GET("/subjects", { params: { query: { after: page.next_after } } }), 200);
    assert(page.subjects.map((s) => s.id).join() === "ts-15" && page.next_after === null, JSON.stringify(page));
  },

  async get_subject_detail() {
    const d = ok(await client.GET("/subjects/{id}", { params: { path: { id: "ts-15" } } }), 200);
    assert(d.id === "ts-15" && d.templates === 2 && d.model_versions.length === 1, JSON.stringify(d));
  },

  async delete_a_subject() {
    const r = await client.DELETE("/subjects/{id}", { params: { path: { id: "ts-15" } } });
    assert(r.response.status === 204, `status ${r.response.status}`);
    problem(await client.GET("/subjects/{id}", { params: { path: { id: "ts-15" } } }), 404, "unknown-subject");
  },

  async problems_as_typed_errors() {
    const grey = new Blob([Buffer.from("P5 320 240 255\n"), new Uint8Array(320 * 240).fill(128)]);
    const p = problem(
      await client.POST("/enroll", { body: { subject: "ts-03", image: [photo("03-1m.jpg"), grey] }, ...multipart }),
      422,
      "no-face",
    );
    assert(p.image === 1, JSON.stringify(p));
    const text = new Blob(["not a photo"], { type: "text/plain" });
    problem(await client.POST("/verify", { body: { subject: "ts-01", image: text }, ...multipart }), 422, "not-an-image");
    problem(await client.POST("/verify", { body: { subject: "nobody", image: b64("01-2m.jpg") } }), 404, "unknown-subject");
    problem(await client.POST("/verify", { body: { subject: "ts-01", image: "%%%" } }), 400, "malformed-request");
    const h = ok(await client.GET("/health"), 200);
    assert(h.subjects === 1 && h.templates === 2, JSON.stringify(h));
  },
};

let passed = 0;
let failed = 0;
for (const [name, check] of Object.entries(checks)) {
  try {
    await check();
    passed++;
    console.log(`ok   typescript ${name}`);
  } catch (e) {
    failed++;
    console.log(`FAIL typescript ${name}\n${e instanceof Error ? e.stack : e}`);
  }
}
console.log(`typescript: ${passed} passed, ${failed} failed`);
process.exitCode = failed ? 1 : 0;
