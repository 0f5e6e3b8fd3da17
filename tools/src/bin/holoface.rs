//! The `holoface` command line; see `holoface --help`.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    let cli = holoface_tools::cli::Cli::parse();
    holoface_tools::cli::init_logging(&cli.log);
    let stop = holoface_process::stop::Stop::new();
    holoface_tools::cli::handle_signals(&stop);
    holoface_tools::cli::run(cli, &stop)
}
