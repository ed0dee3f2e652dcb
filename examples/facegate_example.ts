// facegate from TypeScript on Node >= 18 (fetch, FormData and Blob are built in; no dependencies):
// enrol photos, verify a probe, verify with a head-turn challenge (active liveness). An ES module
// (top-level await); compile it with tsc (or run it with tsx), then:
//
//   node facegate_example.js enroll alice alice-1.jpg alice-2.jpg
//   node facegate_example.js verify alice probe.jpg [--fmr 1e-4]
//   node facegate_example.js verify-challenge alice probe.jpg --left l.jpg [--left l2.jpg] --right r.jpg [--front f.jpg]
//
// verify-challenge asks for a challenge (POST /liveness/challenge), answers each step with the
// photos given for its turn (`front` defaults to the probe; a real client takes a short burst of
// camera frames per step, well inside the step's yaw range) and verifies the probe with them. An
// option given more than once makes a burst: each step gets all its turn's photos (at most the
// challenge's `max_frames_per_step`), sent with `frame_steps`; with one photo per turn, one frame
// per step.
//
// FACEGATE_URL (default http://127.0.0.1:8080) and FACEGATE_API_KEY (if the server has keys) set
// the server. Exit status: 0 enrolled / match, 1 no match, 2 a photo is unusable (no face, a printed photo,
// a failed challenge, ...), 3 model mismatch (enrol the subject again), 4 any other error.
import { readFileSync } from "node:fs";
import { basename } from "node:path";

const PROBLEMS = "https://facegate.dev/problems/";
const BASE_URL = process.env.FACEGATE_URL ?? "http://127.0.0.1:8080";
const KEY = process.env.FACEGATE_API_KEY;

/** An application/problem+json answer; `slug` is the type's last segment (`no-face`, ...). */
class Problem extends Error {
  slug: string;
  // `frame`: the further frame at fault; `reason`: why a head-turn challenge failed.
  constructor(readonly body: { type: string; status: number; title: string; detail: string; image?: number; frame?: number; reason?: string }) {
    super(`${body.type} (${body.status}): ${body.detail}`);
    this.slug = body.type.replace(PROBLEMS, "");
  }
}

/** POST multipart (photos as `image` file parts, then `frames` as `frame` parts; no body when there
 * is nothing to send); retry `overloaded` after Retry-After seconds. */
async function post<T>(path: string, fields: Record<string, string>, photos: string[], frames: string[] = [], attempts = 5): Promise<T> {
  const form = new FormData();
  for (const [name, value] of Object.entries(fields)) form.append(name, value);
  for (const photo of photos) form.append("image", new Blob([readFileSync(photo)]), basename(photo));
  for (const frame of frames) form.append("frame", new Blob([readFileSync(frame)]), basename(frame));
  const empty = Object.keys(fields).length + photos.length + frames.length === 0;
  const headers: Record<string, string> = KEY ? { Authorization: `Bearer ${KEY}` } : {};
  for (let attempt = 1; ; attempt++) {
    const r = await fetch(new URL(path, BASE_URL), { method: "POST", body: empty ? null : form, headers });
    if (r.headers.get("content-type")?.startsWith("application/problem+json")) {
      const problem = new Problem(await r.json());
      if (problem.slug === "overloaded" && attempt < attempts) {
        const delay = Number(r.headers.get("retry-after") ?? "1") || 1;
        console.error(`facegate is busy; retrying in ${delay} s`);
        await new Promise((resolve) => setTimeout(resolve, delay * 1000));
        continue;
      }
      throw problem;
    }
    if (!r.ok) throw new Error(`HTTP ${r.status} from facegate`);
    return (await r.json()) as T;
  }
}

type Turn = "front" | "left" | "right";
type Challenge = { challenge: string; expires_in: number; steps: { turn: Turn; yaw_min: number; yaw_max: number }[]; max_frames_per_step?: number };
type Verdict = {
  match: boolean;
  score: number;
  threshold: number;
  fmr: number;
  liveness?: { attack: boolean; challenge?: { passed: boolean; reason: string | null; steps: { turn: Turn; yaw: number | null; ok: boolean; frames: number }[] } };
};

/** Ask for a challenge, answer each step with the photos of its turn, verify; print the outcome. */
async function verifyChallenge(subject: string, probe: string, photos: Record<Turn, string[]>): Promise<number> {
  const c = await post<Challenge>("/liveness/challenge", {}, []);
  console.log(`challenge of ${c.steps.length} steps: ${c.steps.map((s) => `${s.turn} (${s.yaw_min}..${s.yaw_max} deg)`).join(", ")}`);
  const bursts = c.steps.map((s) => (photos[s.turn].length > 0 ? photos[s.turn] : [probe]).slice(0, c.max_frames_per_step ?? 5));
  const frames = bursts.flat();
  const fields: Record<string, string> = { subject, challenge: c.challenge };
  // Bursts: the 0-based step of each frame, in order.
  if (frames.length > c.steps.length) fields.frame_steps = bursts.flatMap((burst, i) => burst.map(() => i)).join(",");
  const v = await post<Verdict>("/verify", fields, [probe], frames);
  console.log(`${v.match ? "match" : "no match"}: score ${v.score.toFixed(3)}, threshold ${v.threshold.toFixed(3)} at FMR ${v.fmr}`);
  const outcome = v.liveness?.challenge;
  if (!outcome) {
    console.error("the server judged no challenge (liveness is off)");
    return 4;
  }
  for (const s of outcome.steps) {
    console.log(`  ${s.turn}: yaw ${s.yaw === null ? "unknown" : `${s.yaw.toFixed(1)} deg`}, ${s.frames} frame(s), ${s.ok ? "ok" : "not ok"}`);
  }
  if (!outcome.passed) {
    console.error(`the head-turn challenge failed: ${outcome.reason}`);
    return 2;
  }
  console.log("challenge passed");
  return v.match ? 0 : 1;
}

/** The value of the option `name` (removed from `args` with it), if given. */
function option(args: string[], name: string): string | undefined {
  const at = args.indexOf(name);
  return at >= 0 ? args.splice(at, 2)[1] : undefined;
}

/** Every value of the option `name`, which may be given more than once (removed from `args`). */
function options(args: string[], name: string): string[] {
  const values: string[] = [];
  for (let value = option(args, name); value !== undefined; value = option(args, name)) values.push(value);
  return values;
}

const USAGE =
  "usage: facegate_example enroll SUBJECT PHOTO... | verify SUBJECT PHOTO [--fmr 1e-4] | verify-challenge SUBJECT PROBE --left PHOTO... --right PHOTO... [--front PHOTO...] (each option once per photo)";

async function main(argv: string[]): Promise<number> {
  const [command, subject, ...rest] = argv;
  const fmr = option(rest, "--fmr");
  const turns: Record<Turn, string[]> = { front: options(rest, "--front"), left: options(rest, "--left"), right: options(rest, "--right") };
  const challenge = command === "verify-challenge";
  if (!subject || rest.length === 0 || !["enroll", "verify", "verify-challenge"].includes(command ?? "") || (challenge && (turns.left.length === 0 || turns.right.length === 0))) {
    console.error(USAGE);
    return 4;
  }
  try {
    if (challenge) return await verifyChallenge(subject, rest[0] as string, turns);
    if (command === "enroll") {
      const e = await post<{ subject: string; added: number; templates: number }>("/enroll", { subject }, rest);
      console.log(`enrolled ${e.subject}: ${e.added} template(s) added, ${e.templates} in all`);
      return 0;
    }
    const path = fmr ? `/verify?fmr=${encodeURIComponent(fmr)}` : "/verify";
    const v = await post<{ match: boolean; score: number; threshold: number; fmr: number }>(path, { subject }, rest.slice(0, 1));
    console.log(`${v.match ? "match" : "no match"}: score ${v.score.toFixed(3)}, threshold ${v.threshold.toFixed(3)} at FMR ${v.fmr}`);
    return v.match ? 0 : 1;
  } catch (e) {
    if (!(e instanceof Problem)) {
      console.error(`request to facegate at ${BASE_URL} failed: ${e}`);
      return 4;
    }
    if (e.body.reason) {
      console.error(`the head-turn challenge failed: ${e.body.reason} (${e.slug})`);
      return 2;
    }
    if (["no-face", "several-faces", "presentation-attack", "not-an-image", "corrupt-image", "unsupported-format", "too-large"].includes(e.slug)) {
      const which = e.body.frame === undefined ? rest[e.body.image ?? 0] : `frame ${e.body.frame + 1}`;
      console.error(`${which}: ${e.body.detail} (${e.slug}); take another photo`);
      return 2;
    }
    if (e.slug === "model-mismatch") {
      console.error(`${subject} was enrolled with another model version: enrol the subject again`);
      return 3;
    }
    console.error(`facegate refused: ${e.message}`);
    return 4;
  }
}

process.exitCode = await main(process.argv.slice(2));
