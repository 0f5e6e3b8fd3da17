//! The `holoface` command line; see `holoface --help`.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    let cli = holoface_client::cli::Cli::parse();
    holoface_client::cli::init_logging(&cli.log);
    holoface_client::cli::run(cli)
}
