// facegate from TypeScript on Node >= 18 (fetch, FormData and Blob are built in; no dependencies):
// enrol photos, verify a probe. An ES module (top-level await); compile it with tsc (or run it
// with tsx), then:
//
//   node facegate_example.js enroll alice alice-1.jpg alice-2.jpg
//   node facegate_example.js verify alice probe.jpg [--fmr 1e-4]
//
// FACEGATE_URL (default http://127.0.0.1:8080) and FACEGATE_API_KEY (if the server has keys) set
// the server. Exit status: 0 enrolled / match, 1 no match, 2 a photo is unusable (no face, a printed photo, ...),
// 3 model mismatch (enrol the subject again), 4 any other error.
import { readFileSync } from "node:fs";
import { basename } from "node:path";

const PROBLEMS = "https://facegate.dev/problems/";
const BASE_URL = process.env.FACEGATE_URL ?? "http://127.0.0.1:8080";
const KEY = process.env.FACEGATE_API_KEY;

/** An application/problem+json answer; `slug` is the type's last segment (`no-face`, ...). */
class Problem extends Error {
  slug: string;
  constructor(readonly body: { type: string; status: number; title: string; detail: string; image?: number }) {
    super(`${body.type} (${body.status}): ${body.detail}`);
    this.slug = body.type.replace(PROBLEMS, "");
  }
}

/** POST multipart (photos as `image` file parts); retry `overloaded` after Retry-After seconds. */
async function post<T>(path: string, fields: Record<string, string>, photos: string[], attempts = 5): Promise<T> {
  const form = new FormData();
  for (const [name, value] of Object.entries(fields)) form.append(name, value);
  for (const photo of photos) form.append("image", new Blob([readFileSync(photo)]), basename(photo));
  const headers: Record<string, string> = KEY ? { Authorization: `Bearer ${KEY}` } : {};
  for (let attempt = 1; ; attempt++) {
    const r = await fetch(new URL(path, BASE_URL), { method: "POST", body: form, headers });
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

async function main(argv: string[]): Promise<number> {
  const [command, subject, ...rest] = argv;
  const fmrAt = rest.indexOf("--fmr");
  const fmr = fmrAt >= 0 ? rest.splice(fmrAt, 2)[1] : undefined;
  if (!subject || rest.length === 0 || (command !== "enroll" && command !== "verify")) {
    console.error("usage: facegate_example enroll SUBJECT PHOTO... | verify SUBJECT PHOTO [--fmr 1e-4]");
    return 4;
  }
  try {
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
    if (["no-face", "several-faces", "presentation-attack", "not-an-image", "corrupt-image", "unsupported-format", "too-large"].includes(e.slug)) {
      console.error(`${rest[e.body.image ?? 0]}: ${e.body.detail} (${e.slug}); take another photo`);
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
