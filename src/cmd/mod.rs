//! One module per subcommand. Each has `Args` (clap) and `run(Args) -> anyhow::Result<ExitCode>`.
pub mod bench;
pub mod calib;
pub mod common;
pub mod demo;
pub mod eta;
pub mod export;
pub mod mc;
pub mod merge;
pub mod night;
pub mod report;
pub mod setup;
pub mod simulate;
pub mod stats;
pub mod summary;
pub mod target;
pub mod watch;
