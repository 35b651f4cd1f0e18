#include "server/igtl_gateway.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <stdexcept>

#include <spdlog/spdlog.h>

#include "core/errors.h"
#include "image/nifti_io.h"
#include "mesh/vtk_io.h"
#include "protocol/events.h"
#include "protocol/timing_log.h"
#include "protocol/result_outputs.h"

namespace brainshift::server {
namespace {

using protocol::ResultPart;

// Our own outputs: bounded only so that a corrupt header cannot ask for more.
constexpr std::size_t kMaxResultImageBytes = std::size_t{4} << 30;

std::string errno_text() { return std::strerror(errno); }

void set_non_blocking(int fd) {
  const int flags = fcntl(fd, F_GETFL, 0);
  if (flags < 0 || fcntl(fd, F_SETFL, flags | O_NONBLOCK) < 0)
    throw std::runtime_error("OpenIGTLink: fcntl(O_NONBLOCK): " + errno_text());
}

int listen_on(const std::string& bind, int port, int* bound_port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) throw std::runtime_error("OpenIGTLink: socket(): " + errno_text());
  const int on = 1;
  setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &on, sizeof on);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<std::uint16_t>(port));
  const std::string where = bind + ":" + std::to_string(port);
  if (inet_pton(AF_INET, bind.c_str(), &addr.sin_addr) != 1) {
    ::close(fd);
    throw std::runtime_error("OpenIGTLink: \"" + bind + "\" is not an IPv4 address");
  }
  if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) < 0 || ::listen(fd, 16) < 0) {
    const std::string why = errno_text();
    ::close(fd);
    throw std::runtime_error("OpenIGTLink: cannot listen on " + where + ": " + why);
  }
  socklen_t len = sizeof addr;
  getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
  *bound_port = ntohs(addr.sin_port);
  set_non_blocking(fd);
  return fd;
}

std::optional<std::pair<std::string, std::string>> read_part(const CaseStore& store, const std::string& scan_id,
                                                              ResultPart part) {
  for (const auto& name : protocol::stored_file_names(part))
    if (auto bytes = store.read_result_file(scan_id, name)) return std::make_pair(name, std::move(*bytes));
  return std::nullopt;
}

// Runs decode; a failure becomes a problem named in the STATUS, not a lost result.
template <class Decode>
void try_decode(igtl::ResultContent& r, const std::string& name, Decode decode) {
  try {
    decode();
  } catch (const std::exception& e) {
    spdlog::error("OpenIGTLink: scan {}: {} not sent: {}", r.scan_id, name, e.what());
    r.problems.push_back(name + ": " + e.what());
  }
}

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

igtl::ResultContent load_igtl_result(const CaseStore& store, const std::string& scan_id, const LabelTable& labels) {
  const auto record = store.find(scan_id);
  if (!record || record->state != StoredScanState::done) throw InputError("scan " + scan_id + " has no result");
  igtl::ResultContent r;
  r.scan_id = scan_id;
  r.client_scan_id = record->client_scan_id;
  r.result = record->result;
  r.finished_at = record->finished_at.value_or(protocol::utc_now());
  if (auto f = read_part(store, scan_id, ResultPart::kDisplacement))
    try_decode(r, f->first, [&] { r.field = vector_image_from_bytes(f->second, f->first, kMaxResultImageBytes); });
  if (auto f = read_part(store, scan_id, ResultPart::kWarpedImage))
    try_decode(r, f->first,
               [&] { r.warped_image = scalar_image_from_bytes(f->second, f->first, kMaxResultImageBytes); });
  if (auto f = read_part(store, scan_id, ResultPart::kWarpedLabels))
    try_decode(r, f->first,
               [&] { r.warped_labels = label_image_from_bytes(f->second, f->first, kMaxResultImageBytes); });
  for (const LabelEntry& e : labels.entries) {
    const std::string name = protocol::model_file_name(e.name);
    if (auto bytes = store.read_result_file(scan_id, name))
      try_decode(r, name, [&] { r.models.emplace_back(short_name_of(e), read_vtp_bytes(*bytes, name)); });
  }
  return r;
}

IgtlGateway::IgtlGateway(const OpenIgtlinkSettings& settings, const CaseStore& store, LabelTable labels)
    : settings_(settings), store_(store), labels_(std::move(labels)) {
  listen_fd_ = listen_on(settings_.bind, settings_.port, &port_);
  wake_fd_ = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (wake_fd_ < 0) {
    ::close(listen_fd_);
    throw std::runtime_error("OpenIGTLink: eventfd(): " + errno_text());
  }
  if (!is_loopback_ipv4(settings_.bind))
    spdlog::warn("OpenIGTLink on the non-loopback address {}:{} (allow_non_loopback): OpenIGTLink has no "
                 "authentication or encryption, anyone on that network can read every result",
                 settings_.bind, port_);
  spdlog::info("OpenIGTLink gateway listening on {}:{}", settings_.bind, port_);
  thread_ = std::thread([this] { run(); });
}

IgtlGateway::~IgtlGateway() {
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
  }
  wake();
  thread_.join();
  for (auto& c : clients_) ::close(c.fd);
  ::close(wake_fd_);
  ::close(listen_fd_);
}

void IgtlGateway::wake() {
  const std::uint64_t one = 1;
  // Fails only when the counter is saturated, i.e. a wake-up is pending anyway.
  [[maybe_unused]] const ssize_t n = ::write(wake_fd_, &one, sizeof one);
}

void IgtlGateway::publish(const std::string& scan_id) {
  {
    std::lock_guard lock(mutex_);
    pending_.push_back(scan_id);
  }
  wake();
}

void IgtlGateway::publish_deferred(const std::string& scan_id) {
  {
    std::lock_guard lock(mutex_);
    pending_deferred_.push_back(scan_id);
  }
  wake();
}

protocol::OpenIgtlinkInfo IgtlGateway::info() const {
  return {static_cast<std::uint64_t>(port_), connected_.load(), sent_.load(), dropped_.load()};
}

void IgtlGateway::run() {
  // The latest result, for the clients that connect before the next scan.
  for (const auto& record : store_.list_newest_first(1000))
    if (record.state == StoredScanState::done) {
      load_and_send(record.scan_id);
      break;
    }
  std::vector<pollfd> fds;
  for (;;) {
    fds.assign({{wake_fd_, POLLIN, 0}, {listen_fd_, POLLIN, 0}});
    for (const auto& c : clients_)
      fds.push_back({c.fd, static_cast<short>(POLLIN | (c.queue.empty() ? 0 : POLLOUT)), 0});
    if (::poll(fds.data(), fds.size(), 1000) < 0 && errno != EINTR) {
      spdlog::error("OpenIGTLink: poll(): {}", errno_text());
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      continue;
    }
    std::vector<std::string> scans, deferred;
    {
      std::lock_guard lock(mutex_);
      if (stop_) return;
      scans.swap(pending_);
      deferred.swap(pending_deferred_);
    }
    if (fds[0].revents & POLLIN) {
      std::uint64_t count = 0;
      [[maybe_unused]] const ssize_t n = ::read(wake_fd_, &count, sizeof count);
    }
    // Clients first: the sockets polled are the ones in clients_ now.
    std::vector<bool> gone(clients_.size(), false);
    for (std::size_t i = 0; i < clients_.size(); ++i) {
      const short ev = fds[i + 2].revents;
      if (ev & POLLIN) gone[i] = !drain_input(clients_[i]);
      if (!gone[i] && (ev & POLLOUT)) gone[i] = !write_some(clients_[i]);
      if (!gone[i] && (ev & (POLLERR | POLLNVAL | POLLHUP))) {
        close_client(clients_[i], ev & POLLHUP ? "hung up" : "socket error");
        gone[i] = true;
      }
    }
    for (std::size_t i = clients_.size(); i-- > 0;)
      if (gone[i]) clients_.erase(clients_.begin() + static_cast<std::ptrdiff_t>(i));
    connected_ = clients_.size();
    if (fds[1].revents & POLLIN) accept_clients();
    for (const auto& scan_id : scans) load_and_send(scan_id);
    for (const auto& scan_id : deferred) send_deferred(scan_id);
  }
}

void IgtlGateway::send_deferred(const std::string& scan_id) {
  try {
    const auto f = read_part(store_, scan_id, ResultPart::kUncertainty);
    if (!f) return;  // not made (e.g. switched off): nothing to send
    const auto record = store_.find(scan_id);
    const std::string at = record && record->finished_at ? *record->finished_at : protocol::utc_now();
    const ImageF map = scalar_image_from_bytes(f->second, f->first, kMaxResultImageBytes);
    auto m = std::make_shared<const igtl::PackedMessage>(
        igtl::pack_image(igtl::kUncertaintyDevice, map, igtl::time_stamp_from_iso(at)));
    // A client connecting later gets it with the result it belongs to.
    if (latest_scan_id_ == scan_id) latest_.push_back(m);
    for (auto& c : clients_) enqueue(c, {m}, /*supersede=*/false);
    spdlog::info("OpenIGTLink: scan {}: {} sent to {} client(s)", scan_id, igtl::kUncertaintyDevice, clients_.size());
  } catch (const std::exception& e) {
    spdlog::error("OpenIGTLink: scan {}: uncertainty map not sent: {}", scan_id, e.what());
  }
}

void IgtlGateway::load_and_send(const std::string& scan_id) {
  try {
    const auto t0 = std::chrono::steady_clock::now();
    double read_s = 0;
    auto t1 = t0;
    std::vector<igtl::PackedMessage> packed;
    {
      const igtl::ResultContent content = load_igtl_result(store_, scan_id, labels_);  // freed once packed
      read_s = seconds_since(t0);
      t1 = std::chrono::steady_clock::now();
      packed = igtl::encode_result(content);
    }
    std::vector<Shared> messages;
    std::size_t bytes = 0;
    for (auto& m : packed) {
      bytes += m.bytes.size();
      messages.push_back(std::make_shared<const igtl::PackedMessage>(std::move(m)));
    }
    latest_ = messages;
    latest_scan_id_ = scan_id;
    for (auto& c : clients_) enqueue(c, messages);
    spdlog::info("OpenIGTLink: scan {}: {} messages, {:.1f} MB (read {:.3f} s, packed {:.3f} s) to {} client(s)",
                 scan_id, messages.size(), bytes / 1e6, read_s, seconds_since(t1), clients_.size());
  } catch (const std::exception& e) {
    spdlog::error("OpenIGTLink: scan {} not sent: {}", scan_id, e.what());
  }
}

void IgtlGateway::enqueue(Client& c, const std::vector<Shared>& messages, bool supersede) {
  // A new result supersedes what a client has not begun to receive of older
  // ones: a stalled client then holds at most one old message and the
  // latest result, however many results go by (a whole-head field is
  // ~130 MB).
  const std::size_t keep = c.written > 0 ? 1 : 0;
  if (supersede && c.queue.size() > keep) {
    dropped_ += c.queue.size() - keep;
    c.queue.erase(c.queue.begin() + static_cast<std::ptrdiff_t>(keep), c.queue.end());
  }
  for (const auto& m : messages) {
    c.queue.push_back(m);
    // The front message may be half written: it stays, the next one goes.
    while (c.queue.size() > settings_.queue_messages) {
      const auto victim = c.queue.begin() + (c.written > 0 ? 1 : 0);
      c.queue.erase(victim);
      ++dropped_;
    }
  }
}

void IgtlGateway::accept_clients() {
  for (;;) {
    sockaddr_in addr{};
    socklen_t len = sizeof addr;
    const int fd = ::accept4(listen_fd_, reinterpret_cast<sockaddr*>(&addr), &len, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR || errno == ECONNABORTED) return;
      spdlog::warn("OpenIGTLink: accept(): {}", errno_text());
      // Out of descriptors: the pending connection keeps the listening
      // socket readable, so without a pause this would spin.
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      return;
    }
    char ip[INET_ADDRSTRLEN] = "?";
    inet_ntop(AF_INET, &addr.sin_addr, ip, sizeof ip);
    const std::string peer = std::string(ip) + ":" + std::to_string(ntohs(addr.sin_port));
    if (clients_.size() >= settings_.max_clients) {
      spdlog::warn("OpenIGTLink: refused {}: already {} clients (max_clients)", peer, clients_.size());
      ::close(fd);
      continue;
    }
    const int on = 1;
    // A peer that vanished without a FIN is found by keepalive, not kept forever.
    setsockopt(fd, SOL_SOCKET, SO_KEEPALIVE, &on, sizeof on);
    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &on, sizeof on);
    clients_.push_back(Client{fd, peer, {}, 0});
    enqueue(clients_.back(), latest_);
    connected_ = clients_.size();
    spdlog::info("OpenIGTLink: client {} connected ({} message(s) of the latest result queued)", peer,
                 latest_.size());
  }
}

bool IgtlGateway::write_some(Client& c) {
  while (!c.queue.empty()) {
    const std::string_view bytes = c.queue.front()->bytes;
    const ssize_t n = ::send(c.fd, bytes.data() + c.written, bytes.size() - c.written, MSG_NOSIGNAL);
    if (n < 0) {
      if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) return true;
      close_client(c, std::strerror(errno));
      return false;
    }
    c.written += static_cast<std::size_t>(n);
    if (c.written == bytes.size()) {
      c.queue.pop_front();
      c.written = 0;
      ++sent_;
    }
  }
  return true;
}

// The gateway only sends; what a client sends (Slicer may send its own
// messages or queries) is read and discarded so its socket never backs up.
bool IgtlGateway::drain_input(Client& c) {
  char buf[16384];
  // Bounded per round, so a client that floods cannot starve the others.
  for (int round = 0; round < 64; ++round) {
    const ssize_t n = ::recv(c.fd, buf, sizeof buf, 0);
    if (n > 0) continue;
    if (n == 0) {
      close_client(c, "disconnected");
      return false;
    }
    if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) return true;
    close_client(c, std::strerror(errno));
    return false;
  }
  return true;
}

void IgtlGateway::close_client(Client& c, const char* why) {
  spdlog::info("OpenIGTLink: client {} closed ({}), {} unsent message(s) discarded", c.peer, why, c.queue.size());
  ::close(c.fd);
  c.fd = -1;
}

}  // namespace brainshift::server
