//! Data-parallel training over torch.distributed's c10d: a Gloo process group (CPU; libtorch's
//! own copy, through the small shim in `csrc/c10d_shim.cpp`, since tch binds none of
//! torch.distributed), joined the way torchrun, srun or any launcher asks:
//!
//! - `WORLD_SIZE` and `RANK` (or, under srun, `SLURM_STEP_NUM_TASKS` and `SLURM_PROCID`): a world of one, or
//!   neither set, is a plain single-process run;
//! - `MASTER_ADDR` (default 127.0.0.1) and `MASTER_PORT` (default 29500): the rendezvous store.
//!   Rank 0 serves it on exactly that address (not on every interface, c10d's own default),
//!   unless `TORCHELASTIC_USE_AGENT_STORE=True` says the launcher (torchrun) serves it;
//! - `GLOO_SOCKET_IFNAME`: the interface Gloo's connections use; otherwise the loopback
//!   address when the master is on loopback (one machine), else the host name's address.
//! - `LABRIG_DIST_BACKEND`: `gloo` (the default). `nccl` is refused with the reason: this
//!   libtorch is a CPU build.

// The FFI to the shim is this module's whole reason to exist; nothing else in the crate is unsafe.
#![allow(unsafe_code)]

use std::ffi::{CString, c_char, c_void};
use std::net::{IpAddr, ToSocketAddrs};
use tch::Tensor;

unsafe extern "C" {
    fn labrig_c10d_new(
        addr: *const c_char,
        port: i32,
        listen_fd: i32,
        agent_store: i32,
        prefix: *const c_char,
        rank: i32,
        world: i32,
        gloo_host: *const c_char,
        gloo_iface: *const c_char,
        timeout_ms: i64,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
    fn labrig_c10d_free(g: *mut c_void);
    fn labrig_c10d_average_grads(
        g: *mut c_void,
        params: *const *const c_void,
        n: usize,
        extra: *mut f64,
        n_extra: usize,
        err: *mut c_char,
        err_len: usize,
    ) -> i32;
    fn labrig_c10d_broadcast(
        g: *mut c_void,
        tensors: *const *const c_void,
        n: usize,
        root: i32,
        err: *mut c_char,
        err_len: usize,
    ) -> i32;
    fn labrig_c10d_sum(g: *mut c_void, v: *mut f64, err: *mut c_char, err_len: usize) -> i32;
}

#[derive(Debug, thiserror::Error)]
pub enum DistError {
    #[error("{var}={value}: {why}")]
    Env { var: &'static str, value: String, why: String },
    #[error("joining the process group (rank {rank} of {world}, store {addr}:{port}): {why}")]
    Join { rank: usize, world: usize, addr: String, port: u16, why: String },
    #[error("{what} (rank {rank} of {world}): {why}")]
    Collective { what: &'static str, rank: usize, world: usize, why: String },
}

/// Where this process sits in a data-parallel run, as its launcher set it in the environment.
#[derive(Debug, Clone, PartialEq)]
pub struct Launch {
    pub rank: usize,
    pub world: usize,
    pub master_addr: String,
    pub master_port: u16,
    /// The launcher (torchrun's agent) serves the store; `prefix` is its key space.
    pub agent_store: bool,
    pub prefix: String,
    pub gloo_iface: Option<String>,
}

impl Launch {
    /// The launch `get` describes (an environment lookup), or None for a single process.
    pub fn from(get: impl Fn(&str) -> Option<String>) -> Result<Option<Launch>, DistError> {
        let num = |var: &'static str| -> Result<Option<usize>, DistError> {
            get(var)
                .map(|v| {
                    v.trim().parse::<usize>().map_err(|e| DistError::Env { var, value: v.clone(), why: e.to_string() })
                })
                .transpose()
        };
        // Slurm: srun's step variables (a batch script's own SLURM_NTASKS is not a launch).
        let (world, rank) = match (num("WORLD_SIZE")?, num("SLURM_STEP_NUM_TASKS")?) {
            (Some(w), _) => (w, num("RANK")?),
            (None, Some(w)) => (w, num("SLURM_PROCID")?),
            (None, None) => return Ok(None),
        };
        if world <= 1 {
            return Ok(None);
        }
        let Some(rank) = rank else {
            return Err(DistError::Env {
                var: "RANK",
                value: String::new(),
                why: format!("unset, with a world of {world}: the launcher must give each process its rank"),
            });
        };
        if rank >= world {
            return Err(DistError::Env {
                var: "RANK",
                value: rank.to_string(),
                why: format!("must be below WORLD_SIZE={world}"),
            });
        }
        match get("LABRIG_DIST_BACKEND").as_deref() {
            None | Some("gloo") => {}
            Some("nccl") => {
                return Err(DistError::Env {
                    var: "LABRIG_DIST_BACKEND",
                    value: "nccl".into(),
                    why: "this labrig links a CPU libtorch, which has no NCCL: use gloo, or build against a CUDA libtorch"
                        .into(),
                });
            }
            Some(other) => {
                return Err(DistError::Env {
                    var: "LABRIG_DIST_BACKEND",
                    value: other.into(),
                    why: "gloo is the backend this build has".into(),
                });
            }
        }
        let master_port = match get("MASTER_PORT") {
            None => 29500,
            Some(v) => v.trim().parse().map_err(|e: std::num::ParseIntError| DistError::Env {
                var: "MASTER_PORT",
                value: v,
                why: e.to_string(),
            })?,
        };
        let agent_store = get("TORCHELASTIC_USE_AGENT_STORE").is_some_and(|v| v.eq_ignore_ascii_case("true"));
        // torchrun's agent keeps each restart's keys apart (torch's env:// rendezvous does the same).
        let prefix = if agent_store {
            format!("/worker/attempt_{}", get("TORCHELASTIC_RESTART_COUNT").unwrap_or_else(|| "0".into()))
        } else {
            String::new()
        };
        Ok(Some(Launch {
            rank,
            world,
            master_addr: get("MASTER_ADDR").unwrap_or_else(|| "127.0.0.1".into()),
            master_port,
            agent_store,
            prefix,
            gloo_iface: get("GLOO_SOCKET_IFNAME").filter(|s| !s.is_empty()),
        }))
    }

    /// From this process's environment.
    pub fn from_env() -> Result<Option<Launch>, DistError> {
        Launch::from(|k| std::env::var(k).ok())
    }

    fn master_ip(&self) -> Option<IpAddr> {
        (self.master_addr.as_str(), self.master_port).to_socket_addrs().ok()?.map(|a| a.ip()).next()
    }
}

/// A joined process group.
#[derive(Debug)]
pub struct Group {
    ptr: *mut c_void,
    pub rank: usize,
    pub world: usize,
}

// The shim's group is used from one thread at a time (the training loop's).
unsafe impl Send for Group {}
unsafe impl Sync for Group {}

const ERR_LEN: usize = 1024;

fn text(buf: &[u8]) -> String {
    let end = buf.iter().position(|b| *b == 0).unwrap_or(buf.len());
    String::from_utf8_lossy(&buf[..end]).trim().to_owned()
}

impl Group {
    /// Joins the group `launch` describes; waits up to `timeout` for the other ranks.
    pub fn join(launch: &Launch, timeout: std::time::Duration) -> Result<Group, DistError> {
        let join_err = |why: String| DistError::Join {
            rank: launch.rank,
            world: launch.world,
            addr: launch.master_addr.clone(),
            port: launch.master_port,
            why,
        };
        let ip = launch.master_ip();
        // Rank 0 binds the store's socket itself, on the master address alone.
        let listener = if launch.rank == 0 && !launch.agent_store {
            let ip = ip.ok_or_else(|| join_err(format!("MASTER_ADDR {} does not resolve", launch.master_addr)))?;
            Some(
                std::net::TcpListener::bind((ip, launch.master_port))
                    .map_err(|e| join_err(format!("binding the store on {ip}:{}: {e}", launch.master_port)))?,
            )
        } else {
            None
        };
        let fd = listener.map(std::os::fd::IntoRawFd::into_raw_fd).unwrap_or(-1);
        let loopback = ip.is_some_and(|ip| ip.is_loopback());
        let gloo_host = if launch.gloo_iface.is_none() && loopback { ip.map(|i| i.to_string()) } else { None };
        let c = |s: &str| CString::new(s).map_err(|_| join_err(format!("{s:?} holds a NUL byte")));
        let (addr, prefix) = (c(&launch.master_addr)?, c(&launch.prefix)?);
        let host = c(gloo_host.as_deref().unwrap_or(""))?;
        let iface = c(launch.gloo_iface.as_deref().unwrap_or(""))?;
        let mut err = [0u8; ERR_LEN];
        let ptr = unsafe {
            labrig_c10d_new(
                addr.as_ptr(),
                launch.master_port as i32,
                fd,
                launch.agent_store as i32,
                prefix.as_ptr(),
                launch.rank as i32,
                launch.world as i32,
                host.as_ptr(),
                iface.as_ptr(),
                timeout.as_millis() as i64,
                err.as_mut_ptr().cast(),
                ERR_LEN,
            )
        };
        if ptr.is_null() {
            return Err(join_err(text(&err)));
        }
        Ok(Group { ptr, rank: launch.rank, world: launch.world })
    }

    fn collective(&self, what: &'static str, rc: i32, err: &[u8]) -> Result<(), DistError> {
        if rc == 0 {
            return Ok(());
        }
        Err(DistError::Collective { what, rank: self.rank, world: self.world, why: text(err) })
    }

    /// Averages the gradients of `params` over the ranks; `extra` is summed in the same call.
    pub fn average_grads(&self, params: &[Tensor], extra: &mut [f64]) -> Result<(), DistError> {
        let ptrs: Vec<*const c_void> = params.iter().map(|t| t.as_ptr().cast()).collect();
        let mut err = [0u8; ERR_LEN];
        let rc = unsafe {
            labrig_c10d_average_grads(
                self.ptr,
                ptrs.as_ptr(),
                ptrs.len(),
                extra.as_mut_ptr(),
                extra.len(),
                err.as_mut_ptr().cast(),
                ERR_LEN,
            )
        };
        self.collective("averaging the gradients", rc, &err)
    }

    /// Overwrites `tensors` on every rank with rank `root`'s.
    pub fn broadcast(&self, tensors: &[Tensor], root: usize) -> Result<(), DistError> {
        let ptrs: Vec<*const c_void> = tensors.iter().map(|t| t.as_ptr().cast()).collect();
        let mut err = [0u8; ERR_LEN];
        let rc = unsafe {
            labrig_c10d_broadcast(self.ptr, ptrs.as_ptr(), ptrs.len(), root as i32, err.as_mut_ptr().cast(), ERR_LEN)
        };
        self.collective("broadcasting the weights", rc, &err)
    }

    /// The sum of `v` over the ranks; every rank waits here for all the others.
    pub fn sum(&self, v: f64) -> Result<f64, DistError> {
        let mut v = v;
        let mut err = [0u8; ERR_LEN];
        let rc = unsafe { labrig_c10d_sum(self.ptr, &mut v, err.as_mut_ptr().cast(), ERR_LEN) };
        self.collective("waiting for the other ranks", rc, &err)?;
        Ok(v)
    }
}

impl Drop for Group {
    fn drop(&mut self) {
        unsafe { labrig_c10d_free(self.ptr) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn launch(vars: &[(&str, &str)]) -> Result<Option<Launch>, DistError> {
        let m: HashMap<String, String> = vars.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        Launch::from(|k| m.get(k).cloned())
    }

    #[test]
    fn the_launchers_environment_is_read_and_bad_values_are_named() {
        assert_eq!(launch(&[]).unwrap(), None);
        assert_eq!(launch(&[("WORLD_SIZE", "1"), ("RANK", "0")]).unwrap(), None);
        let l = launch(&[("WORLD_SIZE", "2"), ("RANK", "1"), ("MASTER_PORT", "29612")]).unwrap().unwrap();
        assert_eq!((l.rank, l.world, l.master_addr.as_str(), l.master_port), (1, 2, "127.0.0.1", 29612));
        assert!(!l.agent_store && l.prefix.is_empty());
        // torchrun serves the store itself, with a key space per restart.
        let l = launch(&[
            ("WORLD_SIZE", "2"),
            ("RANK", "0"),
            ("TORCHELASTIC_USE_AGENT_STORE", "True"),
            ("TORCHELASTIC_RESTART_COUNT", "3"),
        ])
        .unwrap()
        .unwrap();
        assert!(l.agent_store);
        assert_eq!(l.prefix, "/worker/attempt_3");
        // srun's variables stand in for torchrun's.
        let l = launch(&[("SLURM_STEP_NUM_TASKS", "4"), ("SLURM_PROCID", "3")]).unwrap().unwrap();
        assert_eq!((l.rank, l.world), (3, 4));
        assert_eq!(launch(&[("SLURM_NTASKS", "4"), ("SLURM_PROCID", "0")]).unwrap(), None);
        let e = launch(&[("WORLD_SIZE", "2")]).unwrap_err().to_string();
        assert!(e.contains("RANK") && e.contains("unset"), "{e}");
        let e = launch(&[("WORLD_SIZE", "2"), ("RANK", "2")]).unwrap_err().to_string();
        assert!(e.contains("below WORLD_SIZE=2"), "{e}");
        let e = launch(&[("WORLD_SIZE", "two")]).unwrap_err().to_string();
        assert!(e.starts_with("WORLD_SIZE=two"), "{e}");
        let e = launch(&[("WORLD_SIZE", "2"), ("RANK", "0"), ("LABRIG_DIST_BACKEND", "nccl")]).unwrap_err().to_string();
        assert!(e.contains("no NCCL"), "{e}");
    }

    /// Two ranks in two threads of this process, on loopback: gradients averaged, figures
    /// summed, rank 0's weights broadcast.
    #[test]
    fn two_ranks_average_gradients_and_share_weights() {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let ranks: Vec<_> = (0..2)
            .map(|rank| {
                std::thread::spawn(move || {
                    let l = Launch {
                        rank,
                        world: 2,
                        master_addr: "127.0.0.1".into(),
                        master_port: port,
                        agent_store: false,
                        prefix: String::new(),
                        gloo_iface: None,
                    };
                    let g = Group::join(&l, std::time::Duration::from_secs(30)).unwrap();
                    let p = Tensor::from_slice(&[1.0f32, 2.0, 3.0]).set_requires_grad(true);
                    // Rank r's loss: (r + 1) * sum(p): its gradient is r + 1 everywhere.
                    ((&p * (rank as f64 + 1.0)).sum(tch::Kind::Float)).backward();
                    let mut extra = [rank as f64 + 0.5, 1.0];
                    g.average_grads(std::slice::from_ref(&p), &mut extra).unwrap();
                    let grad = Vec::<f32>::try_from(p.grad()).unwrap();
                    let w = tch::no_grad(|| Tensor::from_slice(&[rank as f32 * 10.0; 4]));
                    g.broadcast(std::slice::from_ref(&w), 0).unwrap();
                    let total = g.sum(rank as f64).unwrap();
                    (grad, extra, Vec::<f32>::try_from(w).unwrap(), total)
                })
            })
            .collect();
        for r in ranks {
            let (grad, extra, w, total) = r.join().unwrap();
            assert_eq!(grad, vec![1.5; 3]);
            assert_eq!(extra, [2.0, 2.0]);
            assert_eq!(w, vec![0.0; 4]);
            assert_eq!(total, 1.0);
        }
    }
}
