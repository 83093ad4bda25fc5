//! `dpslam` command-line interface: a thin layer over the library.

mod cli;

use clap::Parser;

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// mimalloc v3's option numbers (`mi_option_e` in its `mimalloc.h`; the
/// Rust bindings name only the stable ones).
const MI_OPTION_ARENA_EAGER_COMMIT: libmimalloc_sys::mi_option_t = 4;
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Peak resident memory is what users size machines by, and a DP-map run
/// frees and reallocates a lot (lists swell and shrink as particles
/// disagree, dead branches go every step). With mimalloc's defaults (purge
/// freed pages after 10 ms, arenas committed eagerly, so purged pages stay
/// resident until the kernel wants them) mit-csail peaks at ~400 MiB for
/// ~300 MB of live heap; with both off, ~315 MiB, for a little more system
/// time and the same trajectory. The first arena is reserved by the first
/// allocation, before `main`, so this runs from `.preinit_array`, before any
/// constructor allocates; it allocates nothing and sets the options
/// outright, so `MIMALLOC_PURGE_DELAY` and `MIMALLOC_ARENA_EAGER_COMMIT`
/// have no effect on the CLI.
extern "C" fn hand_back_freed_memory() {
    // SAFETY: plain stores to mimalloc's static option table, before any
    // thread or allocation exists.
    unsafe {
        libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, 0);
        libmimalloc_sys::mi_option_set(MI_OPTION_ARENA_EAGER_COMMIT, 0);
    }
}

#[cfg(target_os = "linux")]
#[used]
#[unsafe(link_section = ".preinit_array")]
static HAND_BACK_FREED_MEMORY: extern "C" fn() = hand_back_freed_memory;

fn main() -> std::process::ExitCode {
    #[cfg(not(target_os = "linux"))]
    hand_back_freed_memory();
    let args = cli::Cli::parse();
    match cli::run(args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("dpslam: error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
