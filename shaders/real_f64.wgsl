// Prelude of likelihood.wgsl for adapters with SHADER_F64: f64 throughout.
//
// Vulkan has no f64 `exp` (GLSL.std.450 Exp is 16/32-bit only), so `exp_neg`
// is written out with f64 multiply and add: Cody–Waite reduction by ln 2
// and a Taylor polynomial, accurate to a few ulp, which is what makes the
// scores equal the CPU's (f64, libm) to ~1e-12 instead of ~1e-4.

alias real = f64;

// (node id, density hi, density lo, unused): the density in stops per cell
// length as two f32s whose sum is the f64 value to ~48 bits.
alias EntryWords = vec4<u32>;

fn entry_node(i: u32) -> u32 {
    return entry(i).x;
}

fn entry_density(i: u32) -> real {
    let e = entry(i);
    return f64(bitcast<f32>(e.y)) + f64(bitcast<f32>(e.z));
}

// exp(−x) for finite x (the callers pass x ≥ 0). exp(−x) = 2^−k · exp(−r) with
// r = x − k ln 2 ∈ [−ln2/2, ln2/2]; ln 2 = LN2_HI + LN2_LO where LN2_HI has
// 21 trailing zero bits, so k · LN2_HI is exact (fdlibm's split). The Taylor
// series of exp(−r) to r¹⁴ leaves < 1e-19 relative; 2^−k is built by
// squaring powers of two, which is exact (down to subnormals).
fn exp_neg(x: real) -> real {
    if (x > 745.0) {
        return 0.0;
    }
    if (x < -709.0) {
        return 1.0e308;
    }
    let k = floor(x * 1.4426950408889634 + 0.5);
    let r = (x - k * 6.93147180369123816490e-01) - k * 1.90821492927058770002e-10;
    // Horner form of Σ sⁿ/n!, n ≤ 14, coefficients 1/n! rounded to f64.
    let s = -r;
    var p: real = 1.1470745597729725e-11;
    p = p * s + 1.6059043836821613e-10;
    p = p * s + 2.08767569878681e-09;
    p = p * s + 2.505210838544172e-08;
    p = p * s + 2.755731922398589e-07;
    p = p * s + 2.7557319223985893e-06;
    p = p * s + 2.48015873015873e-05;
    p = p * s + 0.0001984126984126984;
    p = p * s + 0.001388888888888889;
    p = p * s + 0.008333333333333333;
    p = p * s + 0.041666666666666664;
    p = p * s + 0.16666666666666666;
    p = p * s + 0.5;
    p = p * s + 1.0;
    p = p * s + 1.0;
    var e = i32(k);
    var base: real = 0.5;
    if (e < 0) {
        e = -e;
        base = 2.0;
    }
    var scale: real = 1.0;
    loop {
        if (e == 0) {
            break;
        }
        if ((e & 1) == 1) {
            scale = scale * base;
        }
        base = base * base;
        e = e >> 1u;
    }
    return p * scale;
}

// 1 − exp(−x), written as the CPU writes it (src/laser_model.rs), so that
// both round the same way to within an ulp.
fn stop_prob(x: real) -> real {
    return 1.0 - exp_neg(x);
}

