// Prelude of likelihood.wgsl for adapters without SHADER_F64: f32 throughout.

alias real = f32;

// (node id, density in stops per cell length as f32 bits).
alias EntryWords = vec2<u32>;

fn entry_node(i: u32) -> u32 {
    return entry(i).x;
}

fn entry_density(i: u32) -> real {
    return bitcast<f32>(entry(i).y);
}

// exp(−x), x ≥ 0.
fn exp_neg(x: real) -> real {
    return exp(-x);
}

// 1 − exp(−x) to ~1e-7 relative (WGSL has no expm1). `1.0 − exp(−x)` alone
// loses 6e-8 absolute, i.e. 2e-5 relative for an unseen 2-D cell (x ≈ 0.004),
// which biases every beam's sum the same way. Below 0.1 the Taylor series to
// x⁶ is exact to x⁶/720 relative.
fn stop_prob(x: real) -> real {
    if (x < 0.1) {
        return x * (1.0 - x * 0.5 * (1.0 - x * (1.0 / 3.0) * (1.0 - x * 0.25 * (1.0 - x * 0.2 * (1.0 - x * (1.0 / 6.0))))));
    }
    return 1.0 - exp(-x);
}

