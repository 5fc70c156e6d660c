//! `lensrig`: parse, run, map to an exit code (0 success, 2 error with a one-line cause).

mod cli;

use clap::Parser;

fn main() {
    cli::panic::install(std::env::args());
    let parsed = match cli::Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let _ = e.print();
            std::process::exit(code);
        }
    };
    if let Err(e) = cli::run(parsed) {
        let chain: Vec<String> = e.chain().map(|c| c.to_string()).collect();
        let mut line = chain.first().cloned().unwrap_or_default();
        for c in chain.iter().skip(1) {
            if !line.contains(c.as_str()) {
                line.push_str(": ");
                line.push_str(c);
            }
        }
        eprintln!("lensrig: error: {line}");
        std::process::exit(2);
    }
}
