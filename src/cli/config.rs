//! `visnav config default` and `visnav config reference`: a complete commented configuration
//! and the key reference, both generated from the configuration types
//! (`visnav_daemon::config::reference`), so that neither can drift from what `run` accepts.

use std::process::ExitCode;

use visnav::daemon::config::reference;

#[derive(clap::Args, Debug)]
pub struct ConfigArgs {
    #[command(subcommand)]
    pub command: ConfigCommand,
}

#[derive(clap::Subcommand, Debug)]
pub enum ConfigCommand {
    /// Print a complete configuration: every section and key with its default and a comment,
    /// the values to replace marked as placeholders (`visnav config default > visnav.toml`;
    /// from the repository's root `visnav config default | visnav check-config -` passes).
    Default,
    /// Print every key the configuration accepts (dotted path, type, default, unit, range,
    /// meaning) as Markdown: docs/config-reference.md is this output.
    Reference,
}

pub fn run(args: ConfigArgs) -> anyhow::Result<ExitCode> {
    let text = match args.command {
        ConfigCommand::Default => reference::default_config(),
        ConfigCommand::Reference => reference::reference_markdown(),
    };
    print!("{text}");
    Ok(ExitCode::SUCCESS)
}
