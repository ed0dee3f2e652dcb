use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    /// Address to listen on.
    #[arg(long, env = "FACEGATE_BIND", default_value = "127.0.0.1:8080")]
    pub bind: String,
    /// Database URL (SQLite).
    #[arg(long, env = "FACEGATE_DATABASE_URL", default_value = "sqlite://facegate.db")]
    pub database: String,
}

pub fn run(_args: ServeArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("the service has not landed yet")
}
