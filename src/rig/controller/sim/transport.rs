//! The simulated firmware on a thread: [`spawn`] runs it over any `Read + Write` (a serial
//! port, a pty master), [`spawn_pty`] over a fresh pseudo-terminal whose slave a client opens
//! by path. The thread applies the port-level faults (silence, garbage, disconnect) and keeps
//! the observable [`SimState`] current.

use std::io::{self, Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::{Faults, Firmware, SimOptions, SimState};

/// A running simulated board.
pub struct SimHandle {
    pub faults: Arc<Faults>,
    state: Arc<Mutex<SimState>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    _keepalive: Option<Box<dyn Send>>,
}

/// A view of a running board that another thread can hold: its faults and true state.
#[derive(Clone)]
pub struct SimObserver {
    pub faults: Arc<Faults>,
    state: Arc<Mutex<SimState>>,
}

impl SimObserver {
    /// The firmware's true state (locks briefly).
    pub fn state(&self) -> MutexGuard<'_, SimState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl SimHandle {
    /// A cloneable view of the board for another thread.
    pub fn observer(&self) -> SimObserver {
        SimObserver { faults: self.faults.clone(), state: self.state.clone() }
    }

    /// The firmware's true state (locks briefly).
    pub fn state(&self) -> MutexGuard<'_, SimState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Stops the firmware thread and waits for it.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// Runs the firmware on a thread over `port`.
///
/// `port.read` must return within a few milliseconds when no data arrives (`TimedOut`,
/// `WouldBlock` or `Ok(0)`), or simulated motion stalls.
pub fn spawn<T: Read + Write + Send + 'static>(port: T, options: SimOptions) -> SimHandle {
    let mut fw = Firmware::new(&options);
    let state = Arc::new(Mutex::new(fw.snapshot()));
    let faults = Arc::new(Faults::default());
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (state, faults, stop) = (state.clone(), faults.clone(), stop.clone());
        std::thread::spawn(move || run(port, fw, &state, &faults, &stop))
    };
    SimHandle { faults, state, stop, thread: Some(thread), _keepalive: None }
}

/// Creates a pseudo-terminal, runs the firmware on its master side, and returns the slave's
/// path for a client to open with `serialport::new(path, 115200)`.
///
/// # Errors
/// When no pty can be allocated.
#[cfg(unix)]
pub fn spawn_pty(options: SimOptions) -> io::Result<(SimHandle, String)> {
    use serialport::SerialPort;
    let (mut master, slave) = serialport::TTYPort::pair().map_err(io::Error::from)?;
    let path = slave.name().ok_or_else(|| io::Error::other("pty slave has no name"))?;
    master.set_timeout(Duration::from_millis(2)).map_err(io::Error::from)?;
    let mut handle = spawn(master, options);
    // Keep one slave descriptor open so the master never sees a hang-up between clients.
    handle._keepalive = Some(Box::new(slave));
    Ok((handle, path))
}

fn garble(bytes: &[u8]) -> Vec<u8> {
    let mut x: u32 = 0x9E37_79B9;
    bytes
        .iter()
        .map(|&b| {
            if b == b'\n' {
                return b'\n';
            }
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            0x80 | (x as u8) // never valid ASCII, rarely valid UTF-8
        })
        .collect()
}

fn run<T: Read + Write>(mut port: T, mut fw: Firmware, state: &Mutex<SimState>, faults: &Faults, stop: &AtomicBool) {
    let mut buf = [0u8; 256];
    loop {
        if stop.load(Ordering::SeqCst) || faults.disconnect.load(Ordering::SeqCst) {
            return; // drops the port
        }
        let silent = faults.silent.load(Ordering::SeqCst);
        match port.read(&mut buf) {
            Ok(0) => std::thread::sleep(Duration::from_millis(1)),
            Ok(n) => {
                if !silent {
                    fw.receive(&buf[..n], Instant::now());
                }
            }
            Err(e) if matches!(e.kind(), io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted) => {}
            // A pty master reads EIO while no client has the slave open: wait for one.
            Err(_) => std::thread::sleep(Duration::from_millis(2)),
        }
        fw.tick(Instant::now(), faults);
        let out = fw.take_output();
        // The true state is published before the bytes that report it are written: a client
        // that has read a reply (an `ALARM:`) and then looks at the state sees what caused it,
        // however the threads are scheduled.
        if let Ok(mut s) = state.lock() {
            fw.snapshot_into(&mut s);
        }
        if !out.is_empty() && !faults.silent.load(Ordering::SeqCst) {
            let out = if faults.garbage.load(Ordering::SeqCst) { garble(&out) } else { out };
            // A client that stopped reading must not wedge the firmware: drop what won't fit.
            let _ = port.write_all(&out).and_then(|_| port.flush());
        }
    }
}
