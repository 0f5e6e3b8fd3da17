//! A loopback UDP relay that injects faults between a QUIC client and the server: drop everything
//! (a cut link), drop a fraction of datagrams, or delay them. Used by the demo to cut the link part-way
//! and by the fault tests; not meant for production traffic.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::time::Duration;

use tokio::net::UdpSocket;
use tokio::task::JoinHandle;

/// The relay's fault knobs, changeable while it runs.
#[derive(Debug, Default)]
pub struct Faults {
    cut: AtomicBool,
    loss_ppm: AtomicU32,
    delay_us: AtomicU64,
    forwarded: AtomicU64,
    dropped: AtomicU64,
}

impl Faults {
    /// Drops every datagram in both directions while `cut`.
    pub fn set_cut(&self, cut: bool) {
        self.cut.store(cut, Ordering::Relaxed);
    }
    /// Drops this fraction of datagrams (0..=1), independently per datagram.
    pub fn set_loss(&self, fraction: f64) {
        self.loss_ppm
            .store((fraction.clamp(0.0, 1.0) * 1e6) as u32, Ordering::Relaxed);
    }
    /// Delays every datagram by `d` (each direction).
    pub fn set_delay(&self, d: Duration) {
        self.delay_us.store(d.as_micros() as u64, Ordering::Relaxed);
    }
    /// (forwarded, dropped) datagrams so far.
    pub fn counts(&self) -> (u64, u64) {
        (
            self.forwarded.load(Ordering::Relaxed),
            self.dropped.load(Ordering::Relaxed),
        )
    }

    /// Whether to drop a datagram; `rng` is the caller's xorshift state.
    fn drop_one(&self, rng: &mut u64) -> bool {
        if self.cut.load(Ordering::Relaxed) {
            return true;
        }
        let ppm = self.loss_ppm.load(Ordering::Relaxed);
        if ppm == 0 {
            return false;
        }
        *rng ^= *rng << 13;
        *rng ^= *rng >> 7;
        *rng ^= *rng << 17;
        (*rng % 1_000_000) < u64::from(ppm)
    }

    async fn forward(self: &Arc<Self>, rng: &mut u64, sock: &Arc<UdpSocket>, data: &[u8], to: SocketAddr) {
        if self.drop_one(rng) {
            self.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.forwarded.fetch_add(1, Ordering::Relaxed);
        let delay = self.delay_us.load(Ordering::Relaxed);
        if delay == 0 {
            let _ = sock.send_to(data, to).await;
        } else {
            let (sock, data) = (Arc::clone(sock), data.to_vec());
            tokio::spawn(async move {
                tokio::time::sleep(Duration::from_micros(delay)).await;
                let _ = sock.send_to(&data, to).await;
            });
        }
    }
}

/// A running relay; dropping it stops it.
#[derive(Debug)]
pub struct UdpRelay {
    addr: SocketAddr,
    faults: Arc<Faults>,
    task: JoinHandle<()>,
}

impl UdpRelay {
    /// Listens on an ephemeral loopback port and forwards to `upstream` (call inside a tokio runtime).
    pub async fn start(upstream: SocketAddr) -> std::io::Result<Self> {
        let front = Arc::new(UdpSocket::bind(SocketAddr::from(([127, 0, 0, 1], 0))).await?);
        let addr = front.local_addr()?;
        let faults = Arc::new(Faults::default());
        let task = tokio::spawn(run(front, upstream, Arc::clone(&faults)));
        Ok(Self { addr, faults, task })
    }

    /// Where clients connect.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The fault knobs.
    pub fn faults(&self) -> &Arc<Faults> {
        &self.faults
    }
}

impl Drop for UdpRelay {
    fn drop(&mut self) {
        self.task.abort();
    }
}

async fn run(front: Arc<UdpSocket>, upstream: SocketAddr, faults: Arc<Faults>) {
    // One upstream socket per client address, so the server sees distinct peers.
    let mut peers: HashMap<SocketAddr, (Arc<UdpSocket>, JoinHandle<()>)> = HashMap::new();
    let mut buf = vec![0u8; 65_536];
    let mut rng = 0x9E37_79B9_7F4A_7C15_u64;
    while let Ok((n, from)) = front.recv_from(&mut buf).await {
        let up = match peers.get(&from) {
            Some((s, _)) => Arc::clone(s),
            None => {
                let Ok(s) = UdpSocket::bind(SocketAddr::from(([127, 0, 0, 1], 0))).await else {
                    continue;
                };
                let s = Arc::new(s);
                let back = tokio::spawn(backward(
                    Arc::clone(&s),
                    Arc::clone(&front),
                    from,
                    Arc::clone(&faults),
                ));
                peers.insert(from, (Arc::clone(&s), back));
                s
            }
        };
        faults.forward(&mut rng, &up, &buf[..n], upstream).await;
    }
    for (_, (_, t)) in peers {
        t.abort();
    }
}

async fn backward(up: Arc<UdpSocket>, front: Arc<UdpSocket>, client: SocketAddr, faults: Arc<Faults>) {
    let mut buf = vec![0u8; 65_536];
    let mut rng = 0xD1B5_4A32_D192_ED03_u64 ^ u64::from(client.port());
    while let Ok((n, _)) = up.recv_from(&mut buf).await {
        faults.forward(&mut rng, &front, &buf[..n], client).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn forwards_both_ways_and_cuts() {
        let echo = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let echo_addr = echo.local_addr().unwrap();
        tokio::spawn(async move {
            let mut b = [0u8; 64];
            while let Ok((n, from)) = echo.recv_from(&mut b).await {
                let _ = echo.send_to(&b[..n], from).await;
            }
        });
        let relay = UdpRelay::start(echo_addr).await.unwrap();
        let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let mut b = [0u8; 64];
        // Sends `msg` through the relay and waits (at most 2 s) for the echo.
        async fn round_trip(client: &UdpSocket, relay: SocketAddr, msg: &[u8]) -> Vec<u8> {
            client.send_to(msg, relay).await.unwrap();
            let mut b = [0u8; 64];
            let n = tokio::time::timeout(Duration::from_secs(2), client.recv(&mut b))
                .await
                .unwrap()
                .unwrap();
            b[..n].to_vec()
        }
        assert_eq!(round_trip(&client, relay.addr(), b"ping").await, b"ping");

        relay.faults().set_cut(true);
        client.send_to(b"lost", relay.addr()).await.unwrap();
        assert!(
            tokio::time::timeout(Duration::from_millis(200), client.recv(&mut b))
                .await
                .is_err()
        );
        assert_eq!(relay.faults().counts(), (2, 1));

        relay.faults().set_cut(false);
        relay.faults().set_delay(Duration::from_millis(50));
        let t = std::time::Instant::now();
        assert_eq!(round_trip(&client, relay.addr(), b"slow").await, b"slow");
        assert!(t.elapsed() >= Duration::from_millis(100), "{:?}", t.elapsed());
    }

    #[test]
    fn loss_fraction_is_respected() {
        let f = Faults::default();
        f.set_loss(0.25);
        let mut rng = 12345;
        let dropped = (0..100_000).filter(|_| f.drop_one(&mut rng)).count();
        assert!((23_000..27_000).contains(&dropped), "{dropped}");
    }
}
