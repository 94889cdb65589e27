//! A controller for the manipulator bridge: sends the pipette into the first cell the
//! bridge reports, then back out (the README's Rust example).

use std::io::{BufRead, BufReader, Write};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let addr = std::env::args().nth(1).unwrap_or("127.0.0.1:7878".into());
    let s = std::net::TcpStream::connect(&addr)?;
    let (mut out, mut sent) = (s.try_clone()?, false);
    for line in BufReader::new(s).lines() {
        let ev: serde_json::Value = serde_json::from_str(&line?)?;
        match (ev["event"].as_str(), ev["plan"]["goal"].as_str()) {
            (Some("scene"), _) if !sent && ev["cells"][0]["id"].is_u64() => {
                // Tracks where a track node feeds the bridge, else the frame's index.
                let key = if ev["ids"] == "track" {
                    "track"
                } else {
                    "cell"
                };
                writeln!(
                    out,
                    r#"{{"cmd":"approach","{key}":{}}}"#,
                    ev["cells"][0]["id"]
                )?;
                sent = true;
            }
            (Some("arrived"), Some("approach")) => writeln!(out, r#"{{"cmd":"retract"}}"#)?,
            (Some("arrived" | "blocked" | "error"), _) => {
                println!("{ev}");
                break;
            }
            _ => {}
        }
    }
    Ok(())
}
