//! The round-trip floor for stop-and-wait transfers: a minimal blocking UDP ping-pong.
//!
//! `udp_pingpong server ADDR` echoes datagrams until it receives an empty one;
//! `udp_pingpong client ADDR COUNT SIZE` sends COUNT datagrams of SIZE bytes one at a time,
//! each after the previous echo, and prints the seconds of that loop. `scripts/bench-transfer.sh`
//! multiplies nothing: COUNT is the number of blocks of the transfer it compares with, and
//! it times the client process as a whole too.

use std::net::UdpSocket;
use std::process::ExitCode;
use std::time::Instant;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().collect();
    let result = match args.get(1).map(String::as_str) {
        Some("server") if args.len() == 3 => server(&args[2]),
        Some("client") if args.len() == 5 => client(&args[2], &args[3], &args[4]),
        _ => Err("usage: udp_pingpong server ADDR | client ADDR COUNT SIZE".into()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("udp_pingpong: {e}");
            ExitCode::FAILURE
        }
    }
}

fn server(addr: &str) -> Result<(), Box<dyn std::error::Error>> {
    let socket = UdpSocket::bind(addr)?;
    let mut buf = [0u8; 2048];
    loop {
        let (n, peer) = socket.recv_from(&mut buf)?;
        if n == 0 {
            return Ok(());
        }
        socket.send_to(&buf[..n], peer)?;
    }
}

fn client(addr: &str, count: &str, size: &str) -> Result<(), Box<dyn std::error::Error>> {
    let count: usize = count.parse()?;
    let size: usize = size.parse()?;
    let socket = UdpSocket::bind("127.0.0.1:0")?;
    socket.connect(addr)?;
    socket.set_read_timeout(Some(std::time::Duration::from_secs(2)))?;
    let out = vec![0x5a_u8; size];
    let mut buf = [0u8; 2048];
    let started = Instant::now();
    for _ in 0..count {
        socket.send(&out)?;
        socket.recv(&mut buf)?;
    }
    let elapsed = started.elapsed();
    socket.send(&[])?;
    println!("{:.6}", elapsed.as_secs_f64());
    Ok(())
}
