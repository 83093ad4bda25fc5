// Beam likelihoods of the DP-SLAM penetration model, one invocation per
// (candidate, beam). A port of `LaserModel::beam_log_likelihood` (src/laser_model.rs)
// over the flattened DP-map of `src/gpu/flatten.rs`.
//
// Units: every length here is in CELLS, measured from the corner of the
// sensor's own cell, so that f32 keeps ~1e-5 cell precision over a 1000-cell
// trace wherever the robot is in the world (metres or absolute cell indices
// in f32 would lose that far from the origin). 2-D runs the same code with
// z = 0 and a zero z direction, so the z axis is never stepped.

struct Params {
    n_cand: u32,
    n_beams: u32,
    brick_bits: u32,
    table_mask: u32,
    // 2σ², cells².
    two_var: f32,
    // Errors at or beyond this (cells) add nothing.
    max_error: f32,
    // Prior stop density of unseen cells, stops per cell length.
    prior: f32,
    dim: u32,
    _p3: u32,
    _p0: u32,
    _p1: u32,
}

struct Cand {
    // Sensor cell (absolute index), w = the particle's pre-order index (bitcast).
    cell: vec4<i32>,
    // Sensor origin inside its cell, [0, 1) per axis.
    frac: vec4<f32>,
    // Rows of the sensor-to-map rotation.
    r0: vec4<f32>,
    r1: vec4<f32>,
    r2: vec4<f32>,
}

struct Beam {
    // Unit direction in the sensor frame; w = measured range (cells).
    dir: vec4<f32>,
    // x = trace start, y = trace end (cells), z = 1 for "no return", w = 1: score 0.
    span: vec4<f32>,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> cands: array<Cand>;
@group(0) @binding(2) var<storage, read> beams: array<Beam>;
// Open-addressing brick table: xyz = brick key, w = brick index (-1: empty slot).
@group(0) @binding(3) var<storage, read> table: array<vec4<i32>>;
// Per brick, cells_per_brick + 1 offsets into `entries` (cell i: [h[i], h[i+1])).
@group(0) @binding(4) var<storage, read> headers: array<u32>;
// (node id, density in stops per cell length as f32 bits).
@group(0) @binding(5) var<storage, read> entries: array<vec2<u32>>;
// Per node id: (enter, exit) of the depth-first numbering.
@group(0) @binding(6) var<storage, read> numbering: array<vec2<u32>>;
// Beam likelihoods, before the floor.
@group(0) @binding(7) var<storage, read_write> out_l: array<f32>;

// Stands in for +inf (naga rejects infinite literals); no trace is this long.
const BIG: f32 = 1.0e30;

fn brick_hash(b: vec3<i32>) -> u32 {
    return (bitcast<u32>(b.x) * 73856093u) ^ (bitcast<u32>(b.y) * 19349663u) ^ (bitcast<u32>(b.z) * 83492791u);
}

fn find_brick(b: vec3<i32>) -> i32 {
    var s = brick_hash(b) & P.table_mask;
    // The table is at most half full, so an empty slot always ends the probe.
    loop {
        let t = table[s];
        if (t.w < 0) {
            return -1;
        }
        if (all(t.xyz == b)) {
            return t.w;
        }
        s = (s + 1u) & P.table_mask;
    }
    return -1;
}

// Density (stops per cell length) the particle at pre-order `leaf` sees in
// local cell `local` of brick `bi`: the containing entry with the largest
// `enter`, as `resolve` in src/dpmap.rs. -1 when the particle never saw it.
fn resolve(bi: i32, local: u32, leaf: u32) -> f32 {
    let cpb = 1u << (P.brick_bits * P.dim);
    let h = u32(bi) * (cpb + 1u) + local;
    let s = headers[h];
    let e = headers[h + 1u];
    var found = false;
    var best = 0u;
    var rho = -1.0;
    for (var i = s; i < e; i = i + 1u) {
        let en = entries[i];
        let nm = numbering[en.x];
        if (nm.x <= leaf && leaf <= nm.y && (!found || nm.x > best)) {
            found = true;
            best = nm.x;
            rho = bitcast<f32>(en.y);
        }
    }
    return rho;
}

// 1 − exp(−x) to ~1e-7 relative (WGSL has no expm1). `1.0 − exp(−x)` alone
// loses 6e-8 absolute, i.e. 2e-5 relative for an unseen 2-D cell (x ≈ 0.004),
// which biases every beam's sum the same way. Below 0.1 the Taylor series to
// x⁶ is exact to x⁶/720 relative.
fn stop_prob(x: f32) -> f32 {
    if (x < 0.1) {
        return x * (1.0 - x * 0.5 * (1.0 - x * (1.0 / 3.0) * (1.0 - x * 0.25 * (1.0 - x * 0.2 * (1.0 - x * (1.0 / 6.0))))));
    }
    return 1.0 - exp(-x);
}

@compute @workgroup_size(64)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    let idx = (wg.y * nwg.x + wg.x) * 64u + li;
    if (idx >= P.n_cand * P.n_beams) {
        return;
    }
    let c = cands[idx / P.n_beams];
    let b = beams[idx % P.n_beams];
    if (b.span.w > 0.5) {
        // Not scored: likelihood 1, log 0.
        out_l[idx] = 1.0;
        return;
    }
    let ds = b.dir.xyz;
    let dir = vec3<f32>(dot(c.r0.xyz, ds), dot(c.r1.xyz, ds), dot(c.r2.xyz, ds));
    let range = b.dir.w;
    let t0 = b.span.x;
    let t1 = b.span.y;
    let no_return = b.span.z > 0.5;
    let leaf = bitcast<u32>(c.cell.w);

    // Amanatides–Woo set-up as in src/raycast.rs, in cell units.
    let start = c.frac.xyz + dir * t0;
    var k = vec3<i32>(floor(start));
    var step = vec3<i32>(0);
    var tn0 = vec3<f32>(BIG);
    var td = vec3<f32>(0.0);
    for (var i = 0; i < 3; i = i + 1) {
        if (dir[i] > 0.0) {
            step[i] = 1;
            td[i] = 1.0 / dir[i];
            tn0[i] = t0 + (f32(k[i] + 1) - start[i]) / dir[i];
        } else if (dir[i] < 0.0) {
            step[i] = -1;
            td[i] = -1.0 / dir[i];
            tn0[i] = t0 + (f32(k[i]) - start[i]) / dir[i];
        }
    }

    let mask = (1 << P.brick_bits) - 1;
    let bb = vec3<u32>(P.brick_bits);
    var last_key = vec3<i32>(2147483647);
    var last_brick = -1;
    // Boundary times are tn0 + n·td rather than running sums, so that their
    // error stays one rounding instead of growing along 1000-cell traces.
    var n = vec3<f32>(0.0);
    var t = t0;
    // The probability of reaching the current cell is exp(−depth), with the
    // optical depth `depth` = Σ x a compensated (Kahan) sum. A running product
    // `reach *= exp(−x)` compounds one `exp` rounding per crossed cell, and
    // shader `exp` (Vulkan: 3 + 2|x| ulp) rounds with a bias: on lavapipe that
    // product made every 3-D sample's score ~2.4e-4 nats too low (sums of
    // ~2500 beams); one `exp` per use has no such drift.
    var depth = 0.0;
    var depth_c = 0.0;
    // 1 − reach, summed separately: `eval / (1 − reach)` stays exact when
    // every stop probability is tiny, and exp(−depth) stays exact when tiny.
    var miss = 0.0;
    var eval = 0.0;
    let max_steps = u32(3.0 * max(t1 - t0, 0.0)) + 8u;
    for (var it = 0u; it < max_steps && t < t1; it = it + 1u) {
        let tn = tn0 + n * td;
        var axis = 0;
        if (tn.y < tn.x) {
            axis = 1;
        }
        if (tn.z < tn[axis]) {
            axis = 2;
        }
        let t_out = min(tn[axis], t1);
        let len = t_out - t;

        let key = c.cell.xyz + k;
        let bkey = key >> bb;
        if (any(bkey != last_key)) {
            last_key = bkey;
            last_brick = find_brick(bkey);
        }
        var rho = -1.0;
        if (last_brick >= 0) {
            let local = u32(key.x & mask) | (u32(key.y & mask) << P.brick_bits)
                | (u32(key.z & mask) << (2u * P.brick_bits));
            rho = resolve(last_brick, local, leaf);
        }
        var x = rho * len;
        if (rho < 0.0) {
            x = P.prior * len;
        }
        if (x > 0.0) {
            let p = exp(-depth) * stop_prob(x);
            if (p > 0.0) {
                let err = abs(0.5 * (t + t_out) - range);
                if (err < P.max_error) {
                    eval = eval + p * exp(-err * err / P.two_var);
                }
                miss = miss + p;
                let y = x - depth_c;
                let sum = depth + y;
                depth_c = (sum - depth) - y;
                depth = sum;
            }
        }
        t = t_out;
        k[axis] = k[axis] + step[axis];
        n[axis] = n[axis] + 1.0;
    }

    var l = 0.0;
    if (no_return) {
        l = eval + exp(-depth);
    } else if (miss > 0.0) {
        l = eval / miss;
    }
    // The floor and the log are applied on the host in f64: shader `log`
    // may be off by a few ulp, which biases sums over thousands of beams.
    out_l[idx] = l;
}
