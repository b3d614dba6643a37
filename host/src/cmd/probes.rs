//! `subsurf probes`: the debug probes probe-rs can see (the Nucleo's ST-LINK among them).

use probe_rs::probe::list::Lister;

/// List attached debug probes (serial numbers go to `subsurf flash --probe`).
#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<()> {
    let probes = subsurf::flash::list_probes(&Lister::new());
    if probes.is_empty() {
        println!("no debug probes found (USB ST-LINK, CMSIS-DAP, J-Link, ...)");
    }
    for probe in &probes {
        println!("{probe}");
    }
    Ok(())
}
