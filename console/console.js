// The facegate web console: plain JavaScript over the service's own API (same origin). The API key
// lives in the key field only (page memory): it is never written to storage or cookies.

// Errors are collected so that a test (and anyone curious) can read them: window.facegateErrors.
window.facegateErrors = [];
window.addEventListener('error', (e) => window.facegateErrors.push(String(e.message || e)));
window.addEventListener('unhandledrejection', (e) => window.facegateErrors.push(String(e.reason)));

const $ = (selector, root = document) => root.querySelector(selector);

function el(tag, attributes = {}, ...children) {
    const node = document.createElement(tag);
    for (const [key, value] of Object.entries(attributes)) {
        if (key === 'class') node.className = value;
        else if (key === 'text') node.textContent = value;
        else node.setAttribute(key, value);
    }
    for (const child of children) node.append(child);
    return node;
}

function headers() {
    const key = $('#api-key').value.trim();
    return key ? { Authorization: `Bearer ${key}` } : {};
}

/// A failed request: the problem+json body when the server sent one.
class ApiError extends Error {
    constructor(status, problem) {
        super(problem?.detail || `HTTP ${status}`);
        this.status = status;
        this.problem = problem;
    }
}

async function api(method, path, body) {
    const response = await fetch(path, { method, body, headers: headers() });
    const type = response.headers.get('content-type') || '';
    if (!response.ok) {
        const problem = type.includes('json') ? await response.json() : { title: `HTTP ${response.status}`, detail: await response.text() };
        throw new ApiError(response.status, problem);
    }
    if (type.includes('json')) return response.json();
    if (response.status === 204) return null;
    return response.blob();
}

function showProblem(target, error) {
    target.replaceChildren();
    const p = error.problem;
    const box = el('div', { class: 'problem', role: 'alert' });
    if (p) {
        const slug = (p.type || '').split('/').pop();
        box.append(el('strong', { text: `${p.title || 'Refused'} (${error.status})` }), el('p', { text: p.detail || '' }));
        if (p.image !== undefined) box.append(el('p', { text: `Photo number ${p.image + 1}` }));
        if (Array.isArray(p.failures)) {
            const item = (f) => el('li', { text: `${f.component.replaceAll('_', ' ')}: ${fmt(f.value, 1)} (${f.bound} ${fmt(f.limit, 1)})` });
            box.append(el('ul', { class: 'failures' }, ...p.failures.map(item)));
        }
        if (typeof p.score === 'number' && typeof p.threshold === 'number') {
            box.append(el('p', { class: 'liveness', text: `Liveness score ${fmt(p.score)} below the threshold ${fmt(p.threshold)}` }));
        }
        // A failed head-turn challenge refused under --liveness enforce says why.
        if (typeof p.reason === 'string') box.append(el('p', { class: 'reason', text: `Reason: ${p.reason}` }));
        if (slug) box.append(el('code', { text: slug }));
    } else {
        box.append(el('strong', { text: 'The request failed' }), el('p', { text: String(error.message || error) }));
    }
    target.append(box);
    target.scrollIntoView({ block: 'nearest' });
}

const fmt = (x, digits = 3) => (typeof x === 'number' ? x.toFixed(digits) : '–');
const fmtFmr = (f) => (f >= 1e-2 ? `1 in ${Math.round(1 / f)}` : `1 in ${Math.round(1 / f).toLocaleString('en')}`);

// ---------------------------------------------------------------- photo pickers (file, drop, camera)

const pickers = new Map();

function setupPicker(container) {
    const multiple = container.dataset.multiple === 'true';
    container.append($('#picker-template').content.cloneNode(true));
    const input = $('.file', container);
    input.multiple = multiple;
    input.id = `${container.id}-file`;
    if (multiple) $('legend', container).textContent = 'Photos';
    const drop = $('.drop', container);
    const thumbs = $('.thumbs', container);
    const state = { files: [], multiple };
    pickers.set(container.id, state);

    const render = () => {
        thumbs.replaceChildren();
        state.files.forEach((file, index) => {
            const url = URL.createObjectURL(file);
            const img = el('img', { src: url, alt: `Photo ${index + 1}: ${file.name}` });
            img.addEventListener('load', () => URL.revokeObjectURL(url));
            const remove = el('button', { type: 'button', text: 'Remove', 'aria-label': `Remove photo ${index + 1}` });
            remove.addEventListener('click', () => {
                state.files.splice(index, 1);
                render();
            });
            thumbs.append(el('li', {}, img, remove));
        });
    };
    const add = (files) => {
        const images = [...files].filter((f) => f.type.startsWith('image/') || f.type === '');
        state.files = multiple ? state.files.concat(images) : images.slice(0, 1);
        render();
    };
    input.addEventListener('change', () => {
        add(input.files);
        input.value = '';
    });
    drop.addEventListener('dragover', (e) => {
        e.preventDefault();
        drop.classList.add('over');
    });
    drop.addEventListener('dragleave', () => drop.classList.remove('over'));
    drop.addEventListener('drop', (e) => {
        e.preventDefault();
        drop.classList.remove('over');
        add(e.dataTransfer.files);
    });

    const camera = $('.camera', container);
    const video = $('.camera-video', container);
    let stream = null;
    const stop = () => {
        stream?.getTracks().forEach((t) => t.stop());
        stream = null;
        camera.hidden = true;
    };
    $('.camera-start', container).addEventListener('click', async () => {
        if (!navigator.mediaDevices?.getUserMedia) {
            showProblem(container.closest('section').querySelector('.result'), new Error('No camera access here (the page needs https or localhost).'));
            return;
        }
        try {
            stream = await navigator.mediaDevices.getUserMedia({ video: { facingMode: 'user' }, audio: false });
            video.srcObject = stream;
            camera.hidden = false;
            $('.camera-take', container).focus();
        } catch (e) {
            showProblem(container.closest('section').querySelector('.result'), new Error(`The camera is unavailable: ${e.message || e}`));
        }
    });
    $('.camera-stop', container).addEventListener('click', stop);
    $('.camera-take', container).addEventListener('click', () => {
        const canvas = el('canvas');
        canvas.width = video.videoWidth;
        canvas.height = video.videoHeight;
        canvas.getContext('2d').drawImage(video, 0, 0);
        canvas.toBlob((blob) => {
            if (blob) add([new File([blob], `camera-${Date.now()}.jpg`, { type: 'image/jpeg' })]);
            if (!multiple) stop();
        }, 'image/jpeg', 0.92);
    });
}

function photos(id) {
    return pickers.get(id).files;
}

// ---------------------------------------------------------------- what was found: box, landmarks, pose, timings

/// The photo with the face box, the 58 landmarks and the eye and mouth centres drawn over it.
async function overlay(file, report) {
    const bitmap = await createImageBitmap(file);
    const canvas = el('canvas', { class: 'overlay', role: 'img', 'aria-label': 'The photo with the face box and the 58 landmarks' });
    canvas.width = bitmap.width;
    canvas.height = bitmap.height;
    const g = canvas.getContext('2d');
    g.drawImage(bitmap, 0, 0);
    const unit = Math.max(1.5, Math.max(bitmap.width, bitmap.height) / 300);
    const b = report.face.box;
    g.lineWidth = unit;
    g.strokeStyle = '#00e5ff';
    g.strokeRect(b.x, b.y, b.width, b.height);
    // Landmarks the fitted head hides (the far side of a turned face) are drawn hollow.
    const visible = report.landmarks.visible;
    g.fillStyle = '#ffd400';
    g.strokeStyle = '#ffd400';
    report.landmarks.points.forEach(([x, y], i) => {
        g.beginPath();
        g.arc(x, y, unit * 1.2, 0, 2 * Math.PI);
        if (visible && visible[i] === false) g.stroke(); else g.fill();
    });
    g.fillStyle = '#ff3b6b';
    for (const [x, y] of Object.values(report.landmarks.keypoints)) {
        g.beginPath();
        g.arc(x, y, unit * 2, 0, 2 * Math.PI);
        g.fill();
    }
    canvas.dataset.points = String(report.landmarks.points.length);
    return canvas;
}

function table(rows, caption) {
    const t = el('table');
    if (caption) t.append(el('caption', { class: 'muted', text: caption }));
    for (const [k, v] of rows) t.append(el('tr', {}, el('th', { scope: 'row', text: k }), el('td', { text: v })));
    return t;
}

/// "58 points", and how many of them the fitted head shows when the service says.
function landmarkCount(landmarks) {
    const n = landmarks.points.length;
    if (!Array.isArray(landmarks.visible)) return `${n} points`;
    return `${n} points, ${landmarks.visible.filter(Boolean).length} visible`;
}

function faceDetails(report) {
    const parts = [];
    const pose = report.pose;
    const angles = (p) => `${fmt(p.yaw, 1)}°, ${fmt(p.pitch, 1)}°, ${fmt(p.roll, 1)}°`;
    const rows = [
        ['Faces found', String(report.faces_found ?? 1)],
        ['Detector score', fmt(report.face.score, 2)],
        ['Landmarks', landmarkCount(report.landmarks)],
        ['Pose (yaw, pitch, roll)', pose ? angles(pose) : 'unknown (no 3D model)'],
    ];
    // /analyze only: the pose of the detector's five key points, which the head-turn challenge judges.
    if (report.key_point_pose) rows.push(['Pose from the five key points', angles(report.key_point_pose)]);
    parts.push(table(rows, 'The face used'));
    const q = report.quality;
    if (q) {
        const deg = (v) => (typeof v === 'number' ? `${fmt(v, 1)}°` : 'unknown');
        parts.push(table([
            ['Quality score', `${fmt(q.score, 0)} / 100`],
            ['Eye distance', `${fmt(q.inter_eye_px, 0)} px`],
            ['Sharpness', fmt(q.sharpness, 1)],
            ['Brightness, contrast', `${fmt(q.brightness, 0)}, ${fmt(q.contrast, 0)}`],
            ['Light evenness', fmt(q.illumination_uniformity, 2)],
            ['|Yaw|, |pitch|', `${deg(q.yaw_abs_deg)}, ${deg(q.pitch_abs_deg)}`],
            ['Mirror agreement', typeof q.mirror_agreement === 'number' ? fmt(q.mirror_agreement, 3) : 'not measured (no embedding)'],
        ], 'Photo quality'));
    }
    // Absent when the server runs with liveness off.
    const l = report.liveness;
    if (l) {
        parts.push(table([
            ['Liveness', `${l.attack ? 'attack' : 'live'} (score ${fmt(l.score, 3)})`],
            ['Liveness model', l.model],
        ], 'Live face or printed photo'));
    }
    if (report.timings) {
        const rows = Object.entries(report.timings).map(([k, v]) => [k.replace(/_ms$/, '').replace('_', ' '), `${fmt(v, 1)} ms`]);
        parts.push(table(rows, 'Time per stage'));
    }
    return parts;
}

async function reportView(file, report, head) {
    const side = el('div', {}, ...head, ...faceDetails(report));
    return el('div', { class: 'report' }, el('div', {}, await overlay(file, report)), side);
}

function scoreBar(score, threshold) {
    // Cosine-like scores (at most 1): from a little below the lower of score and threshold up to 1.
    const lo = Math.max(-1, Math.min(score, threshold) - 0.2);
    const pos = (x) => `${Math.min(100, Math.max(0, ((x - lo) / (1 - lo)) * 100))}%`;
    // Positions through the CSSOM: the page's Content-Security-Policy refuses inline style attributes.
    const mark = (cls, x) => {
        const span = el('span', { class: cls });
        span.style.left = pos(x);
        return span;
    };
    return el('div', { class: 'bar', role: 'img', 'aria-label': `score ${fmt(score)} against threshold ${fmt(threshold)}` },
        mark('threshold', threshold), mark('score', score));
}

// ---------------------------------------------------------------- views

function busy(form, on) {
    for (const b of form.querySelectorAll('button')) b.disabled = on;
    form.setAttribute('aria-busy', on ? 'true' : 'false');
}

function needPhoto(target, files) {
    if (files.length > 0) return false;
    showProblem(target, new Error('Choose a photo first.'));
    return true;
}

$('#enrol-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const form = e.target;
    const target = $('#enrol-result');
    const subject = $('#enrol-subject').value.trim();
    const files = photos('enrol-picker');
    if (needPhoto(target, files)) return;
    const body = new FormData();
    body.append('subject', subject);
    for (const f of files) body.append('image', f, f.name);
    busy(form, true);
    target.replaceChildren(el('p', { class: 'muted', text: 'Enrolling…' }));
    try {
        const r = await api('POST', '/enroll', body);
        const views = [];
        for (const image of r.images) {
            views.push(await reportView(files[image.index], image, [el('h3', { text: `Photo ${image.index + 1}` })]));
        }
        target.replaceChildren(
            el('p', { class: 'decision match', id: 'enrol-outcome', text: `Enrolled ${r.subject}: ${r.added} photo(s) added, ${r.templates} in all` }),
            el('p', { class: 'muted', text: `Model ${r.model_version}` }),
            ...views,
        );
        target.scrollIntoView({ block: 'start' });
        pickers.get('enrol-picker').files = [];
        $('#enrol-picker .thumbs').replaceChildren();
        refreshSubjectIds();
    } catch (error) {
        showProblem(target, error);
    } finally {
        busy(form, false);
    }
});

$('#verify-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const form = e.target;
    const target = $('#verify-result');
    const files = photos('verify-picker');
    if (needPhoto(target, files)) return;
    const body = new FormData();
    body.append('subject', $('#verify-subject').value.trim());
    body.append('image', files[0], files[0].name);
    busy(form, true);
    target.replaceChildren(el('p', { class: 'muted', text: 'Verifying…' }));
    try {
        const r = await api('POST', `/verify?fmr=${encodeURIComponent($('#verify-fmr').value)}`, body);
        const decision = el('p', { class: `decision ${r.match ? 'match' : 'nomatch'}`, id: 'verify-decision', text: r.match ? `Match: ${r.subject}` : `No match: not ${r.subject}` });
        const why = el('p', {
            text: `Score ${fmt(r.score)} ${r.match ? '≥' : '<'} threshold ${fmt(r.threshold)}, the threshold at false match rate ${fmtFmr(r.fmr)} for a subject with ${r.templates_compared} photo(s)` +
                (typeof r.best_template === 'number' ? `; best against enrolled photo ${r.best_template + 1}.` : '.'),
        });
        target.replaceChildren(await reportView(files[0], r, [decision, why, scoreBar(r.score, r.threshold), el('p', { class: 'muted', text: `Model ${r.model_version}` })]));
        target.scrollIntoView({ block: 'start' });
    } catch (error) {
        showProblem(target, error);
    } finally {
        busy(form, false);
    }
});

$('#identify-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const form = e.target;
    const target = $('#identify-result');
    const files = photos('identify-picker');
    if (needPhoto(target, files)) return;
    const body = new FormData();
    body.append('image', files[0], files[0].name);
    busy(form, true);
    target.replaceChildren(el('p', { class: 'muted', text: 'Searching…' }));
    try {
        const r = await api('POST', `/identify?k=${encodeURIComponent($('#identify-k').value || '5')}`, body);
        const best = r.candidates.find((c) => c.match);
        const decision = el('p', { class: `decision ${best ? 'match' : 'nomatch'}`, id: 'identify-decision', text: best ? `Match: ${best.subject}` : 'No enrolled subject matches' });
        const t = el('table', {}, el('tr', {}, ...['Subject', 'Score', 'Threshold', 'Match'].map((h) => el('th', { scope: 'col', text: h }))));
        for (const c of r.candidates) {
            t.append(el('tr', {}, el('td', { text: c.subject }), el('td', { text: fmt(c.score) }), el('td', { text: fmt(c.threshold) }), el('td', { text: c.match ? 'yes' : 'no' })));
        }
        const note = el('p', { class: 'muted', text: `${r.subjects_searched} subject(s) searched; false match rate ${fmtFmr(r.fmr)} per comparison.` });
        target.replaceChildren(await reportView(files[0], r, [decision, t, note]));
        target.scrollIntoView({ block: 'start' });
    } catch (error) {
        showProblem(target, error);
    } finally {
        busy(form, false);
    }
});

// ---------------------------------------------------------------- verify with the camera: the head-turn challenge

const TURNS = { front: 'Look straight at the camera', left: 'Turn your head to your left', right: 'Turn your head to your right' };
/// How long a step waits for its burst before the best frames seen (else the last one) are sent anyway.
const STEP_TIMEOUT_MS = 20000;
/// A step's burst: at most this many frames (or the challenge's `max_frames_per_step`, if fewer);
/// a burst of at least BURST_MIN ends when the person leaves the pose.
const BURST_MAX = 5;
const BURST_MIN = 3;
/// Where a frame is well inside a step's range: |yaw| at most 6° ahead, 20° to 45° to the asked side.
const BANDS = { front: [-6, 6], left: [20, 45], right: [-45, -20] };
/// The pause before looking again after a frame with no face or pose, another person's face
/// (`followed`), or a busy server. After a frame read, the next look follows at once (one
/// /analyze at a time): a pose held for a tenth of a second is caught, where a pause between all
/// looks missed most such frames.
const RETRY_MS = 300;
/// The probe's range when the challenge has no `front` step to borrow one from.
const FRONT = { turn: 'front', yaw_min: -10, yaw_max: 10 };

const degrees = (x) => (typeof x === 'number' ? `${x.toFixed(1)}°` : 'unknown');
const range = (step) => `yaw ${step.yaw_min}° to ${step.yaw_max}°`;
const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

class Cancelled extends Error {}

/// The challenge under way: { cancelled, stream, video }.
let capture = null;

function stopCapture() {
    if (!capture) return;
    capture.cancelled = true;
    capture.stream?.getTracks().forEach((t) => t.stop());
    capture = null;
    $('#camera-video').srcObject = null;
    $('#camera-live').hidden = true;
}

async function openCamera(run) {
    if (!navigator.mediaDevices?.getUserMedia) throw new Error('No camera access here (the page needs https or localhost).');
    try {
        run.stream = await navigator.mediaDevices.getUserMedia({ video: { facingMode: 'user', width: { ideal: 640 }, height: { ideal: 480 } }, audio: false });
    } catch (e) {
        throw new Error(`The camera is unavailable: ${e.message || e}`);
    }
    if (run.cancelled) throw new Cancelled();
    run.video.srcObject = run.stream;
    $('#camera-live').hidden = false;
    await run.video.play().catch(() => {});
    const deadline = Date.now() + 10000;
    while (run.video.readyState < 2 || run.video.videoWidth === 0) {
        if (run.cancelled) throw new Cancelled();
        if (Date.now() > deadline) throw new Error('The camera gave no picture.');
        await sleep(50);
    }
}

/// The camera's current frame as a JPEG file, as the camera sees it (the preview alone is mirrored).
function grab(video) {
    const canvas = el('canvas');
    canvas.width = video.videoWidth;
    canvas.height = video.videoHeight;
    canvas.getContext('2d').drawImage(video, 0, 0);
    return new Promise((resolve, reject) => {
        canvas.toBlob((blob) => (blob ? resolve(new File([blob], `frame-${Date.now()}.jpg`, { type: 'image/jpeg' })) : reject(new Error('The camera frame could not be encoded.'))), 'image/jpeg', 0.92);
    });
}

/// The largest face /analyze finds in a frame: its box and its yaw as
/// the challenge judges it (`key_point_pose`; null without a pose). Null when it finds no face
/// (or is busy).
async function faceIn(file) {
    const body = new FormData();
    body.append('image', file, file.name);
    try {
        const r = await api('POST', '/analyze', body);
        const face = r.faces[0];
        if (!face) return null;
        const yaw = face.key_point_pose?.yaw;
        return { yaw: typeof yaw === 'number' ? yaw : null, box: face.face?.box ?? null };
    } catch (error) {
        if (error instanceof ApiError && (error.status === 422 || error.status === 503)) return null;
        throw error;
    }
}

/// Looks in a row at another face after which the page follows that one (the person left and came
/// back elsewhere in the picture).
const REFOLLOW_LOOKS = 10;

/// Whether `box` is the face the page follows (`run.followed`, from the probe photo on): its centre
/// within one face width of the last followed face's, as a person moves between two looks. A face
/// further away is someone else's, larger than the person's in that frame: its yaw is not the
/// person's, so the frame is not taken (the server, following the person's face through the
/// frames, would judge theirs). Before the probe is taken every face counts.
function followed(run, box) {
    if (!box || !run.followed) return true;
    const centre = (b) => [b.x + b.width / 2, b.y + b.height / 2];
    const last = run.followed;
    const near = Math.hypot(centre(box)[0] - centre(last)[0], centre(box)[1] - centre(last)[1]) <= last.width;
    run.strayLooks = near ? 0 : (run.strayLooks ?? 0) + 1;
    if (near || run.strayLooks >= REFOLLOW_LOOKS) {
        run.followed = box;
        run.strayLooks = 0;
        return true;
    }
    return false;
}

/// The part of `step`'s range a frame should lie in: its band (BANDS) clamped into the range, or
/// the whole range if they do not overlap.
function band(step) {
    const [lo, hi] = [Math.max(BANDS[step.turn][0], step.yaw_min), Math.min(BANDS[step.turn][1], step.yaw_max)];
    return lo <= hi ? [lo, hi] : [step.yaw_min, step.yaw_max];
}

/// A burst of up to `want` frames for `step`, taken while the person holds the pose: frames whose
/// yaw lies well inside the step's range (`band`), not the first past its boundary. When the
/// step's time is up: those taken so far, else the in-range frames closest to the band's middle,
/// else the last frame taken (the server judges it). `inRange` says whether the frames lie in the step's range, `late` that the
/// time was up.
async function burstFor(run, step, want, seen) {
    const deadline = Date.now() + STEP_TIMEOUT_MS;
    const [lo, hi] = band(step);
    const taken = [];
    for (;;) {
        if (run.cancelled) throw new Cancelled();
        const file = await grab(run.video);
        const face = await faceIn(file);
        if (run.cancelled) throw new Cancelled();
        const stray = face !== null && !followed(run, face.box);
        const yaw = face === null || stray ? null : face.yaw;
        const inRange = yaw !== null && yaw >= step.yaw_min && yaw <= step.yaw_max;
        const inside = inRange && yaw >= lo && yaw <= hi;
        if (inRange) taken.push({ file, yaw, inside, box: face.box });
        const well = taken.filter((t) => t.inside);
        seen.textContent = stray ? 'Another face is larger than yours: keep only yourself in view' : yaw === null ? 'No face seen in the last frame' : `Seen: yaw ${degrees(yaw)}${inside ? ', well inside' : inRange ? `, in range: aim for ${lo}° to ${hi}°` : ''} (${well.length} of ${want} taken)`;
        if (well.length >= want || (well.length >= Math.min(BURST_MIN, want) && !inside)) return { frames: well, inRange: true };
        if (Date.now() >= deadline) {
            if (taken.length === 0) return { frames: [{ file, yaw }], inRange: false, late: true };
            const middle = (lo + hi) / 2;
            const best = well.length > 0 ? well : taken.sort((a, b) => Math.abs(a.yaw - middle) - Math.abs(b.yaw - middle)).slice(0, want);
            return { frames: best, inRange: true, late: true };
        }
        if (yaw === null) await sleep(RETRY_MS);
    }
}

function stepItems(plan) {
    return plan.map((step, i) => el('li', { 'data-state': 'pending', 'data-turn': step.turn, ...(step.probe ? { 'data-probe': 'true' } : { 'data-step': String(i) }) },
        el('span', { text: `${step.probe ? 'Probe photo' : `Step ${i}`}: ${TURNS[step.turn]} (${range(step)})` }),
        el('span', { class: 'state muted', text: ' · waiting' })));
}

function challengeOutcome(r, steps) {
    const c = r.liveness?.challenge;
    if (!c) {
        const why = r.liveness ? 'The server reported no challenge outcome.' : 'Liveness is off on this server: the challenge was not judged.';
        return [el('p', { id: 'camera-challenge', class: 'muted', text: why })];
    }
    const verdict = el('p', { id: 'camera-challenge', class: `decision ${c.passed ? 'match' : 'nomatch'}`, text: c.passed ? 'Challenge passed' : `Challenge failed: ${c.reason || 'no reason given'}` });
    const t = el('table', { id: 'camera-challenge-steps' }, el('caption', { class: 'muted', text: 'The head-turn challenge as the server read each step\'s frames' }),
        el('tr', {}, ...['Step', 'Turn', 'Asked', 'Frames', 'Median yaw', 'In range'].map((h) => el('th', { scope: 'col', text: h }))));
    c.steps.forEach((s, i) => {
        t.append(el('tr', { 'data-ok': String(s.ok) }, el('td', { text: String(i + 1) }), el('td', { text: s.turn }),
            el('td', { text: steps[i] ? range(steps[i]) : '–' }), el('td', { text: typeof s.frames === 'number' ? String(s.frames) : '–' }),
            el('td', { text: degrees(s.yaw) }), el('td', { text: s.ok ? 'yes' : 'no' })));
    });
    return [verdict, t];
}

async function runChallenge(run, subject, target) {
    target.replaceChildren(el('p', { class: 'muted', text: 'Starting the camera…' }));
    await openCamera(run);
    const challenge = await api('POST', '/liveness/challenge');
    if (run.cancelled) throw new Cancelled();
    const front = challenge.steps.find((s) => s.turn === 'front') ?? FRONT;
    const plan = [{ turn: 'front', yaw_min: front.yaw_min, yaw_max: front.yaw_max, probe: true }, ...challenge.steps];
    const items = stepItems(plan);
    const list = $('#camera-steps');
    list.dataset.steps = String(challenge.steps.length);
    list.replaceChildren(...items);
    target.replaceChildren(el('p', { class: 'muted', text: `Challenge of ${challenge.steps.length} steps, valid for ${challenge.expires_in} s.` }));
    const burst = Math.min(BURST_MAX, challenge.max_frames_per_step ?? BURST_MAX);
    const taken = [];
    for (const [i, step] of plan.entries()) {
        items[i].dataset.state = 'current';
        items[i].setAttribute('aria-current', 'step');
        $('.state', items[i]).textContent = ' · now';
        $('#camera-seen').textContent = 'Looking…';
        $('#camera-instruction').textContent = `${step.probe ? 'Probe photo' : `Step ${i} of ${challenge.steps.length}`}: ${TURNS[step.turn]} (${range(step)})`;
        const got = await burstFor(run, step, step.probe ? 1 : burst, $('#camera-seen'));
        items[i].removeAttribute('aria-current');
        items[i].dataset.state = got.inRange ? 'done' : 'timeout';
        const yaws = got.frames.map((f) => degrees(f.yaw)).join(', ');
        $('.state', items[i]).textContent = !got.late ? ` · taken at yaw ${yaws}`
            : got.inRange ? ` · time up: the best frame(s) in range (yaw ${yaws}) go to the server` : ` · time up: the last frame (yaw ${yaws}) goes to the server`;
        taken.push(got.frames);
        // The person is the one in the probe photo: the page follows that face from here on.
        if (step.probe) run.followed = got.frames[0].box ?? null;
    }
    $('#camera-cancel').disabled = true;
    $('#camera-instruction').textContent = 'All frames taken.';
    target.replaceChildren(el('p', { class: 'muted', text: 'Verifying…' }));
    const body = new FormData();
    body.append('subject', subject);
    body.append('image', taken[0][0].file, 'probe.jpg');
    body.append('challenge', challenge.challenge);
    // Each step's burst in step order, `frame_steps` naming each frame's step (0-based).
    const frameSteps = [];
    taken.slice(1).forEach((frames, i) => frames.forEach((f, j) => {
        body.append('frame', f.file, `step-${i + 1}-${j + 1}.jpg`);
        frameSteps.push(i);
    }));
    body.append('frame_steps', frameSteps.join(','));
    const r = await api('POST', '/verify', body);
    const decision = el('p', { class: `decision ${r.match ? 'match' : 'nomatch'}`, id: 'camera-decision', text: r.match ? `Match: ${r.subject}` : `No match: not ${r.subject}` });
    const why = el('p', { text: `Score ${fmt(r.score)} ${r.match ? '≥' : '<'} threshold ${fmt(r.threshold)} at false match rate ${fmtFmr(r.fmr)}.` });
    target.replaceChildren(await reportView(taken[0][0].file, r, [decision, why, scoreBar(r.score, r.threshold), ...challengeOutcome(r, challenge.steps)]));
    target.scrollIntoView({ block: 'start' });
}

$('#camera-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const form = e.target;
    const target = $('#camera-result');
    const subject = $('#camera-subject').value.trim();
    if (!subject) {
        showProblem(target, new Error('Enter the subject id first.'));
        return;
    }
    stopCapture();
    const run = { cancelled: false, stream: null, video: $('#camera-video') };
    capture = run;
    $('#camera-steps').replaceChildren();
    delete $('#camera-steps').dataset.steps;
    $('#camera-instruction').textContent = '';
    $('#camera-seen').textContent = '';
    $('#camera-start').disabled = true;
    $('#camera-cancel').disabled = false;
    form.setAttribute('aria-busy', 'true');
    try {
        await runChallenge(run, subject, target);
    } catch (error) {
        if (error instanceof Cancelled) target.replaceChildren(el('p', { id: 'camera-cancelled', text: 'Cancelled: nothing was sent for verification.' }));
        else showProblem(target, error);
    } finally {
        if (capture === run) stopCapture();
        $('#camera-start').disabled = false;
        $('#camera-cancel').disabled = true;
        form.setAttribute('aria-busy', 'false');
    }
});
$('#camera-cancel').addEventListener('click', stopCapture);

// ---------------------------------------------------------------- subjects

let pendingDelete = null;

async function loadSubjects() {
    const target = $('#subjects-result');
    try {
        const all = [];
        let after = null;
        do {
            const page = await api('GET', `/subjects?limit=1000${after ? `&after=${encodeURIComponent(after)}` : ''}`);
            all.push(...page.subjects);
            after = page.next_after;
        } while (after);
        if (all.length === 0) {
            target.replaceChildren(el('p', { class: 'muted', id: 'subjects-empty', text: 'No subject is enrolled.' }));
            return all;
        }
        const t = el('table', { id: 'subjects-table' }, el('tr', {}, ...['Subject', 'Photos', 'Updated', ''].map((h) => el('th', { scope: 'col', text: h }))));
        for (const s of all) {
            const inspect = el('button', { type: 'button', text: 'Inspect', 'aria-label': `Inspect ${s.id}` });
            inspect.addEventListener('click', () => showSubject(s.id));
            const remove = el('button', { type: 'button', class: 'danger', text: 'Delete', 'aria-label': `Delete ${s.id}`, 'data-subject': s.id });
            remove.addEventListener('click', () => {
                pendingDelete = s.id;
                $('#delete-text').textContent = `Delete ${s.id} and all its ${s.templates} template(s)? This cannot be undone.`;
                $('#delete-dialog').showModal();
            });
            t.append(el('tr', { 'data-subject': s.id }, el('td', { text: s.id }), el('td', { text: String(s.templates) }),
                el('td', { text: new Date(s.updated_at).toLocaleString() }), el('td', {}, el('div', { class: 'row' }, inspect, remove))));
        }
        target.replaceChildren(t);
        return all;
    } catch (error) {
        showProblem(target, error);
        return [];
    }
}

async function showSubject(id) {
    const target = $('#subject-detail');
    try {
        const s = await api('GET', `/subjects/${encodeURIComponent(id)}`);
        const rows = [['Subject', s.id], ['Photos enrolled', String(s.templates)], ['Enrolled', new Date(s.created_at).toLocaleString()]];
        for (const v of s.model_versions) rows.push([`Model ${v.model_version}`, `${v.templates} template(s)`]);
        target.replaceChildren(el('h3', { text: s.id }), table(rows));
    } catch (error) {
        showProblem(target, error);
    }
}

$('#delete-dialog').addEventListener('close', async () => {
    const id = pendingDelete;
    pendingDelete = null;
    if ($('#delete-dialog').returnValue !== 'confirm' || !id) return;
    try {
        await api('DELETE', `/subjects/${encodeURIComponent(id)}`);
        $('#subject-detail').replaceChildren(el('p', { id: 'delete-outcome', text: `${id} was deleted.` }));
        await loadSubjects();
        refreshSubjectIds();
    } catch (error) {
        showProblem($('#subject-detail'), error);
    }
});
$('#subjects-refresh').addEventListener('click', loadSubjects);

async function refreshSubjectIds() {
    try {
        const page = await api('GET', '/subjects?limit=1000');
        $('#subject-ids').replaceChildren(...page.subjects.map((s) => el('option', { value: s.id })));
    } catch {
        // The key may be missing yet: the list is only a convenience.
    }
    refreshHealth();
}

async function refreshHealth() {
    try {
        const h = await api('GET', '/health');
        $('#health').textContent = `Service ${h.status} · model ${h.model_version} · ${h.subjects} subject(s), ${h.templates} template(s)`;
    } catch (error) {
        $('#health').textContent = `Service unreachable: ${error.message}`;
    }
}

// ---------------------------------------------------------------- avatar

let viewer = null;

async function showAvatar(glb) {
    const THREE = await import('./vendor/viewer.js');
    const host = $('#viewer');
    if (!viewer) {
        const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
        renderer.outputColorSpace = THREE.SRGBColorSpace;
        renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
        host.append(renderer.domElement);
        renderer.domElement.id = 'viewer-canvas';
        const scene = new THREE.Scene();
        scene.background = new THREE.Color(0x20242a);
        scene.add(new THREE.AmbientLight(0xffffff, 2.2));
        const light = new THREE.DirectionalLight(0xffffff, 1.2);
        light.position.set(0.3, 0.5, 1);
        scene.add(light);
        const camera = new THREE.PerspectiveCamera(30, 1, 0.01, 10);
        const controls = new THREE.OrbitControls(camera, renderer.domElement);
        controls.enableDamping = true;
        controls.enablePan = false;
        viewer = { THREE, renderer, scene, camera, controls, model: null };
        const resize = () => {
            const w = host.clientWidth || 320;
            renderer.setSize(w, w, true);
            camera.aspect = 1;
            camera.updateProjectionMatrix();
        };
        new ResizeObserver(resize).observe(host);
        resize();
        // Keyboard rotation for people who do not drag.
        host.addEventListener('keydown', (e) => {
            const step = 0.15;
            const rotate = { ArrowLeft: [step, 0], ArrowRight: [-step, 0], ArrowUp: [0, step], ArrowDown: [0, -step] }[e.key];
            if (!rotate || !viewer.model) return;
            e.preventDefault();
            viewer.model.rotation.y += rotate[0];
            viewer.model.rotation.x += rotate[1];
        });
        renderer.setAnimationLoop(() => {
            controls.update();
            renderer.render(scene, camera);
            if (viewer.model) renderer.domElement.dataset.rendered = 'true';
        });
    }
    const url = URL.createObjectURL(glb);
    try {
        const gltf = await new THREE.GLTFLoader().loadAsync(url);
        if (viewer.model) viewer.scene.remove(viewer.model);
        const model = gltf.scene;
        const box = new THREE.Box3().setFromObject(model);
        const centre = box.getCenter(new THREE.Vector3());
        model.position.sub(centre);
        viewer.scene.add(model);
        viewer.model = model;
        const size = box.getSize(new THREE.Vector3()).length();
        viewer.camera.position.set(0, 0, size * 1.9);
        viewer.camera.near = size / 100;
        viewer.camera.far = size * 10;
        viewer.camera.updateProjectionMatrix();
        viewer.controls.target.set(0, 0, 0);
        viewer.controls.update();
    } finally {
        URL.revokeObjectURL(url);
    }
}

$('#avatar-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const form = e.target;
    const target = $('#avatar-result');
    const files = photos('avatar-picker');
    if (needPhoto(target, files)) return;
    const make = () => {
        const body = new FormData();
        body.append('image', files[0], files[0].name);
        return body;
    };
    busy(form, true);
    target.replaceChildren(el('p', { class: 'muted', text: 'Fitting the 3D model…' }));
    try {
        const [glb, png] = await Promise.all([api('POST', '/avatar', make()), api('POST', '/frontalize', make())]);
        $('#avatar-views').hidden = false;
        const old = $('#frontal').src;
        $('#frontal').src = URL.createObjectURL(png);
        if (old.startsWith('blob:')) URL.revokeObjectURL(old);
        const link = $('#avatar-download');
        if (link.href.startsWith('blob:')) URL.revokeObjectURL(link.href);
        link.href = URL.createObjectURL(glb);
        await showAvatar(glb);
        target.replaceChildren(el('p', { id: 'avatar-outcome', text: `Avatar ready (${Math.round(glb.size / 1024)} kB glTF).` }));
        target.scrollIntoView({ block: 'start' });
    } catch (error) {
        showProblem(target, error);
    } finally {
        busy(form, false);
    }
});

// ---------------------------------------------------------------- navigation

function show(view) {
    const name = ['enrol', 'verify', 'camera', 'identify', 'subjects', 'avatar'].includes(view) ? view : 'enrol';
    if (name !== 'camera') stopCapture();
    for (const section of document.querySelectorAll('.view')) section.hidden = section.id !== `view-${name}`;
    for (const link of document.querySelectorAll('nav a')) {
        if (link.dataset.view === name) link.setAttribute('aria-current', 'page');
        else link.removeAttribute('aria-current');
    }
    if (name === 'subjects') loadSubjects();
}

window.addEventListener('hashchange', () => show(location.hash.slice(1)));
for (const container of document.querySelectorAll('.picker')) setupPicker(container);
$('#api-key').addEventListener('change', refreshSubjectIds);
show(location.hash.slice(1));
refreshSubjectIds();
document.body.dataset.ready = 'true';
