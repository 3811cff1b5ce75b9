// labrig's shim over libtorch's c10d (torch.distributed's C++ core), which tch does not bind:
// a Gloo process group over a TCPStore rendezvous, and the three collectives data-parallel
// training needs (gradient averaging, broadcast from a root, barrier). Every entry point
// catches C++ exceptions and hands their text back, so a peer that dies or times out becomes
// a Rust error instead of an abort.

#include <ATen/ATen.h>
#include <torch/csrc/distributed/c10d/PrefixStore.hpp>
#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#include <torch/csrc/distributed/c10d/TCPStore.hpp>

#include <chrono>
#include <cstring>
#include <string>
#include <vector>

namespace {

struct Group {
  c10::intrusive_ptr<c10d::Store> store;
  c10::intrusive_ptr<c10d::ProcessGroupGloo> pg;
  int world;
};

void fail(char *err, size_t len, const std::string &what) {
  if (err && len) {
    std::strncpy(err, what.c_str(), len - 1);
    err[len - 1] = '\0';
  }
}

// The gradients of `params` (zeros for one that has none yet), flattened into one buffer.
std::vector<at::Tensor> grads_of(at::Tensor **params, size_t n) {
  std::vector<at::Tensor> g;
  g.reserve(n);
  for (size_t i = 0; i < n; ++i) {
    at::Tensor &p = *params[i];
    if (!p.mutable_grad().defined()) p.mutable_grad() = at::zeros_like(p);
    g.push_back(p.mutable_grad());
  }
  return g;
}

at::Tensor flat(const std::vector<at::Tensor> &ts) {
  std::vector<at::Tensor> v;
  v.reserve(ts.size());
  for (const auto &t : ts) v.push_back(t.detach().reshape({-1}).to(at::kFloat));
  return at::cat(v);
}

void unflat(const at::Tensor &buf, const std::vector<at::Tensor> &ts) {
  int64_t at_ = 0;
  for (const auto &t : ts) {
    auto n = t.numel();
    at::NoGradGuard no_grad;
    const_cast<at::Tensor &>(t).copy_(buf.narrow(0, at_, n).view(t.sizes()));
    at_ += n;
  }
}

}  // namespace

extern "C" {

// Joins the group: rank 0 serves the store on `listen_fd` (a socket bound to addr:port, or -1
// to let c10d bind `port` itself); `agent_store` = 1 when the launcher (torchrun) serves it.
void *labrig_c10d_new(const char *addr, int port, int listen_fd, int agent_store, const char *prefix, int rank,
                      int world, const char *gloo_host, const char *gloo_iface, long timeout_ms, char *err,
                      size_t err_len) {
  try {
    c10d::TCPStoreOptions o;
    o.port = static_cast<std::uint16_t>(port);
    o.isServer = rank == 0 && !agent_store;
    o.numWorkers = agent_store ? std::nullopt : std::optional<std::size_t>(world);
    o.waitWorkers = false;
    o.timeout = std::chrono::milliseconds(timeout_ms);
    if (o.isServer && listen_fd >= 0) o.masterListenFd = listen_fd;
    c10::intrusive_ptr<c10d::Store> store = c10::make_intrusive<c10d::TCPStore>(std::string(addr), o);
    if (prefix && *prefix) store = c10::make_intrusive<c10d::PrefixStore>(std::string(prefix), store);
    auto opts = c10d::ProcessGroupGloo::Options::create_default(std::chrono::milliseconds(timeout_ms));
    opts->devices.clear();
    if (gloo_iface && *gloo_iface)
      opts->devices.push_back(c10d::ProcessGroupGloo::createDeviceForInterface(gloo_iface));
    else if (gloo_host && *gloo_host)
      opts->devices.push_back(c10d::ProcessGroupGloo::createDeviceForHostname(gloo_host));
    else
      opts->devices.push_back(c10d::ProcessGroupGloo::createDefaultDevice());
    auto pg = c10::make_intrusive<c10d::ProcessGroupGloo>(store, rank, world, opts);
    return new Group{store, pg, world};
  } catch (const std::exception &e) {
    fail(err, err_len, e.what());
    return nullptr;
  }
}

void labrig_c10d_free(void *g) { delete static_cast<Group *>(g); }

// Averages the gradients of `params` over the group, and sums `extra` (per-rank figures: the
// loss, a refusal flag) in the same all-reduce. Returns 0, or -1 with `err` set.
int labrig_c10d_average_grads(void *g, at::Tensor **params, size_t n, double *extra, size_t n_extra, char *err,
                              size_t err_len) {
  try {
    auto *grp = static_cast<Group *>(g);
    auto grads = grads_of(params, n);
    auto ex = at::empty({static_cast<int64_t>(n_extra)}, at::kFloat);
    for (size_t i = 0; i < n_extra; ++i) ex[i] = static_cast<float>(extra[i]);
    std::vector<at::Tensor> buf{at::cat({flat(grads), ex})};
    grp->pg->allreduce(buf)->wait();
    auto total = buf[0].numel() - static_cast<int64_t>(n_extra);
    unflat(buf[0].narrow(0, 0, total) / grp->world, grads);
    auto tail = buf[0].narrow(0, total, static_cast<int64_t>(n_extra)).to(at::kDouble).contiguous();
    std::memcpy(extra, tail.data_ptr<double>(), n_extra * sizeof(double));
    return 0;
  } catch (const std::exception &e) {
    fail(err, err_len, e.what());
    return -1;
  }
}

// Overwrites `tensors` everywhere with `root`'s.
int labrig_c10d_broadcast(void *g, at::Tensor **tensors, size_t n, int root, char *err, size_t err_len) {
  try {
    auto *grp = static_cast<Group *>(g);
    std::vector<at::Tensor> ts;
    for (size_t i = 0; i < n; ++i) ts.push_back(*tensors[i]);
    std::vector<at::Tensor> buf{flat(ts)};
    c10d::BroadcastOptions o;
    o.rootRank = root;
    grp->pg->broadcast(buf, o)->wait();
    unflat(buf[0], ts);
    return 0;
  } catch (const std::exception &e) {
    fail(err, err_len, e.what());
    return -1;
  }
}

// The sum of `v` over the group (a barrier that also carries a figure).
int labrig_c10d_sum(void *g, double *v, char *err, size_t err_len) {
  try {
    auto *grp = static_cast<Group *>(g);
    std::vector<at::Tensor> buf{at::full({1}, *v, at::kDouble)};
    grp->pg->allreduce(buf)->wait();
    *v = buf[0].item<double>();
    return 0;
  } catch (const std::exception &e) {
    fail(err, err_len, e.what());
    return -1;
  }
}

}  // extern "C"
