// Beam likelihoods of the DP-SLAM penetration model, one invocation per
// (candidate, beam). A port of `LaserModel::beam_log_likelihood` (src/laser_model.rs)
// over the flattened DP-map of `src/gpu/flatten.rs`.
//
// This file is the body; the host puts one of two preludes in front of it
// (src/gpu/mod.rs, `shader_source`): `real_f64.wgsl` (the adapter has
// SHADER_F64: every length, weight and sum in f64, exp by a polynomial, so
// that scores equal the CPU's to ~1e-12) or `real_f32.wgsl` (f32 everywhere,
// scores within ~2e-4 of the CPU's). The prelude defines the scalar type
// `real`, the entry layout (`EntryWords`, read by `entry_node` and
// `entry_density`), `exp_neg` and `stop_prob`. Host values travel as (hi, lo) f32 pairs, `wide` joins them:
// exact to ~48 bits in f64 mode, the f32 value in f32 mode.
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
    dim: u32,
    // Elements per chunk of the split entry and header arrays, as powers of two.
    entry_shift: u32,
    header_shift: u32,
    _p2: u32,
    // (hi, lo) pairs. 2σ², cells².
    two_var: vec2<f32>,
    // Errors at or beyond this (cells) add nothing.
    max_error: vec2<f32>,
    // Prior stop density of unseen cells, stops per cell length.
    prior: vec2<f32>,
    _p3: vec2<f32>,
}

// Each `_hi`/`_lo` pair is one value split in two f32s (see `wide`).
struct Cand {
    // Sensor cell (absolute index), w = the particle's pre-order index (bitcast).
    cell: vec4<i32>,
    // Sensor origin inside its cell, [0, 1) per axis.
    frac_hi: vec4<f32>,
    frac_lo: vec4<f32>,
    // Rows of the sensor-to-map rotation.
    r0_hi: vec4<f32>,
    r0_lo: vec4<f32>,
    r1_hi: vec4<f32>,
    r1_lo: vec4<f32>,
    r2_hi: vec4<f32>,
    r2_lo: vec4<f32>,
}

struct Beam {
    // Unit direction in the sensor frame; w = measured range (cells).
    dir_hi: vec4<f32>,
    dir_lo: vec4<f32>,
    // x = trace start, y = trace end (cells); in `span_hi` only: z = 1 for
    // "no return", w = 1: not scored (log-likelihood 0).
    span_hi: vec4<f32>,
    span_lo: vec4<f32>,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> cands: array<Cand>;
@group(0) @binding(2) var<storage, read> beams: array<Beam>;
// Open-addressing brick table: xyz = brick key, w = brick index (-1: empty slot).
@group(0) @binding(3) var<storage, read> table: array<vec4<i32>>;
// Per brick slot, cells_per_brick + 1 offsets into the entries (cell i:
// [h[i], h[i+1])), split over two bindings: see `header`.
@group(0) @binding(4) var<storage, read> headers0: array<u32>;
@group(0) @binding(8) var<storage, read> headers1: array<u32>;
// (node id, density in stops per cell length) in the prelude's layout,
// split over four bindings: see `entry`. A large map exceeds one binding
// (128 MiB on lavapipe); WGSL cannot index bindings, hence the branches.
@group(0) @binding(5) var<storage, read> entries0: array<EntryWords>;
@group(0) @binding(9) var<storage, read> entries1: array<EntryWords>;
@group(0) @binding(10) var<storage, read> entries2: array<EntryWords>;
@group(0) @binding(11) var<storage, read> entries3: array<EntryWords>;
// Per node id: (enter, exit) of the depth-first numbering.
@group(0) @binding(6) var<storage, read> numbering: array<vec2<u32>>;
// Beam likelihoods, before the floor.
@group(0) @binding(7) var<storage, read_write> out_l: array<real>;

// Stands in for +inf (naga rejects infinite literals); no trace is this long.
const BIG: real = 1.0e30;

// Header word i: chunk i >> header_shift, at i & mask.
fn header(i: u32) -> u32 {
    let j = i & ((1u << P.header_shift) - 1u);
    if ((i >> P.header_shift) == 0u) {
        return headers0[j];
    }
    return headers1[j];
}

// Entry i: chunk i >> entry_shift, at i & mask.
fn entry(i: u32) -> EntryWords {
    let j = i & ((1u << P.entry_shift) - 1u);
    let c = i >> P.entry_shift;
    if (c == 0u) {
        return entries0[j];
    }
    if (c == 1u) {
        return entries1[j];
    }
    if (c == 2u) {
        return entries2[j];
    }
    return entries3[j];
}

fn wide(v: vec2<f32>) -> real {
    return real(v.x) + real(v.y);
}

fn wide3(hi: vec4<f32>, lo: vec4<f32>) -> vec3<real> {
    return vec3<real>(hi.xyz) + vec3<real>(lo.xyz);
}

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
fn resolve(bi: i32, local: u32, leaf: u32) -> real {
    let cpb = 1u << (P.brick_bits * P.dim);
    let h = u32(bi) * (cpb + 1u) + local;
    let s = header(h);
    let e = header(h + 1u);
    var found = false;
    var best = 0u;
    var at = 0u;
    for (var i = s; i < e; i = i + 1u) {
        let nm = numbering[entry_node(i)];
        if (nm.x <= leaf && leaf <= nm.y && (!found || nm.x > best)) {
            found = true;
            best = nm.x;
            at = i;
        }
    }
    if (!found) {
        return -1.0;
    }
    return entry_density(at);
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
    if (b.span_hi.w > 0.5) {
        // Not scored: likelihood 1, log 0.
        out_l[idx] = 1.0;
        return;
    }
    let ds = wide3(b.dir_hi, b.dir_lo);
    let dir = vec3<real>(
        dot(wide3(c.r0_hi, c.r0_lo), ds),
        dot(wide3(c.r1_hi, c.r1_lo), ds),
        dot(wide3(c.r2_hi, c.r2_lo), ds),
    );
    let range = wide(vec2<f32>(b.dir_hi.w, b.dir_lo.w));
    let t0 = wide(vec2<f32>(b.span_hi.x, b.span_lo.x));
    let t1 = wide(vec2<f32>(b.span_hi.y, b.span_lo.y));
    let no_return = b.span_hi.z > 0.5;
    let two_var = wide(P.two_var);
    let max_error = wide(P.max_error);
    let prior = wide(P.prior);
    let leaf = bitcast<u32>(c.cell.w);

    // Amanatides–Woo set-up as in src/raycast.rs, in cell units.
    let start = wide3(c.frac_hi, c.frac_lo) + dir * t0;
    var k = vec3<i32>(floor(start));
    var step = vec3<i32>(0);
    var tn0 = vec3<real>(BIG);
    var td = vec3<real>(0.0);
    for (var i = 0; i < 3; i = i + 1) {
        if (dir[i] > 0.0) {
            step[i] = 1;
            td[i] = 1.0 / dir[i];
            tn0[i] = t0 + (real(k[i] + 1) - start[i]) / dir[i];
        } else if (dir[i] < 0.0) {
            step[i] = -1;
            td[i] = -1.0 / dir[i];
            tn0[i] = t0 + (real(k[i]) - start[i]) / dir[i];
        }
    }

    let mask = (1 << P.brick_bits) - 1;
    let bb = vec3<u32>(P.brick_bits);
    var last_key = vec3<i32>(2147483647);
    var last_brick = -1;
    // Boundary times are tn0 + n·td rather than running sums, so that their
    // error stays one rounding instead of growing along 1000-cell traces.
    var n = vec3<real>(0.0);
    var t = t0;
    // The probability of reaching the current cell is exp(−depth), with the
    // optical depth `depth` = Σ x a compensated (Kahan) sum. A running product
    // `reach *= exp(−x)` compounds one `exp` rounding per crossed cell, and
    // shader `exp` (Vulkan: 3 + 2|x| ulp) rounds with a bias: on lavapipe that
    // product made every 3-D sample's score ~2.4e-4 nats too low (sums of
    // ~2500 beams); one `exp` per use has no such drift.
    var depth: real = 0.0;
    var depth_c: real = 0.0;
    // 1 − reach, summed separately: `eval / (1 − reach)` stays exact when
    // every stop probability is tiny, and exp(−depth) stays exact when tiny.
    var miss: real = 0.0;
    var eval: real = 0.0;
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
        var rho: real = -1.0;
        if (last_brick >= 0) {
            let local = u32(key.x & mask) | (u32(key.y & mask) << P.brick_bits)
                | (u32(key.z & mask) << (2u * P.brick_bits));
            rho = resolve(last_brick, local, leaf);
        }
        var x = rho * len;
        if (rho < 0.0) {
            x = prior * len;
        }
        if (x > 0.0) {
            let p = exp_neg(depth) * stop_prob(x);
            if (p > 0.0) {
                let err = abs(0.5 * (t + t_out) - range);
                if (err < max_error) {
                    eval = eval + p * exp_neg(err * err / two_var);
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

    var l: real = 0.0;
    if (no_return) {
        l = eval + exp_neg(depth);
    } else if (miss > 0.0) {
        l = eval / miss;
    }
    // The floor and the log are applied on the host in f64: shader `log`
    // may be off by a few ulp, which biases sums over thousands of beams.
    out_l[idx] = l;
}
