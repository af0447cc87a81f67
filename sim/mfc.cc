// MFC command queue and DMA legality, the shared MIC line server, the atomic unit (see mfc.h).
#include "sim/mfc.h"

#include <algorithm>
#include <cstdio>
#include <cstring>

#include "include/raystream/raystream.h"

namespace rs::sim {
namespace {

std::string Hex(uint64_t x) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "0x%llx", static_cast<unsigned long long>(x));
  return buf;
}

// 128-B lines touched by [ea, ea + size): a partial line costs a whole one.
uint64_t LinesTouched(Ea ea, uint64_t size) {
  if (size == 0) return 0;
  return ((ea + size - 1) >> 7) - (ea >> 7) + 1;
}

constexpr uint8_t kPoison = 0xFF;  // as float: NaN; as index: UINT32_MAX

}  // namespace

const char* CostName(Cost c) {
  switch (c) {
    case Cost::kCompute:
      return "compute";
    case Cost::kDma:
      return "dma";
    case Cost::kAtomic:
      return "atomic";
    case Cost::kCache:
      return "cache";
    case Cost::kIdle:
      return "idle";
  }
  return "?";
}

uint64_t CycleBreakdown::Total() const {
  uint64_t t = 0;
  for (const uint64_t c : cycles) t += c;
  return t;
}

void CycleBreakdown::Merge(const CycleBreakdown& o) {
  for (int i = 0; i < kNumCosts; ++i) cycles[i] += o.cycles[i];
}

void SpuClock::Charge(Cost c, uint64_t cycles) {
  now_ += cycles;
  const int bucket = redirect_ >= 0 ? redirect_ : static_cast<int>(c);
  spent_.cycles[bucket] += cycles;
}

// ------------------------------------------------------------------------------------------
// MainMemory

Ea MainMemory::NextEa() const {
  if (regions_.empty()) return kMainMemoryBase;
  Ea top = 0;
  for (const Region& r : regions_) top = std::max(top, r.end);
  return (top + kRegionAlign - 1) / kRegionAlign * kRegionAlign;
}

Ea MainMemory::Register(const void* data, size_t bytes, std::string name, bool writable) {
  return RegisterAt(NextEa(), data, bytes, std::move(name), writable);
}

Ea MainMemory::RegisterAt(Ea ea, const void* data, size_t bytes, std::string name,
                          bool writable) {
  if (ea == 0 || ea % 128 != 0 || ea + bytes < ea) {
    throw Error("main memory: region '" + name + "' at " + Hex(ea) +
                " must start on a nonzero 128-byte boundary");
  }
  if (bytes == 0) return ea;
  Region r;
  r.begin = ea;
  r.end = ea + bytes;
  r.host = static_cast<uint8_t*>(const_cast<void*>(data));
  r.name = std::move(name);
  r.writable = writable;
  auto it = std::upper_bound(regions_.begin(), regions_.end(), r.begin,
                             [](Ea a, const Region& x) { return a < x.begin; });
  if ((it != regions_.end() && it->begin < r.end) ||
      (it != regions_.begin() && std::prev(it)->end > r.begin)) {
    throw Error("main memory: region '" + r.name + "' overlaps a registered region");
  }
  regions_.insert(it, std::move(r));
  return ea;
}

const MainMemory::Region* MainMemory::Lookup(Ea ea, uint64_t bytes) const {
  auto it = std::upper_bound(regions_.begin(), regions_.end(), ea,
                             [](Ea a, const Region& x) { return a < x.begin; });
  if (it == regions_.begin() || ea + bytes < ea) return nullptr;
  const Region& r = *std::prev(it);
  return r.end < ea + bytes ? nullptr : &r;
}

uint8_t* MainMemory::Find(Ea ea, uint64_t bytes, bool write) const {
  const Region* r = Lookup(ea, bytes);
  if (r == nullptr || (write && !r->writable)) return nullptr;
  return r->host + (ea - r->begin);
}

uint8_t* MainMemory::Check(Ea ea, uint64_t bytes, bool write, const std::string& op) const {
  const Region* r = Lookup(ea, bytes);
  if (r == nullptr) {
    throw Error(op + ": effective-address range [" + Hex(ea) + ", +" + std::to_string(bytes) +
                ") is not inside registered main memory");
  }
  if (write && !r->writable) {
    throw Error(op + ": main-memory region '" + r->name + "' is read-only");
  }
  return r->host + (ea - r->begin);
}

// ------------------------------------------------------------------------------------------
// MemoryController

MemoryController::MemoryController(uint32_t line_cycles) : line_cycles_(line_cycles) {
  if (line_cycles_ == 0) throw Error("mic_line_cycles must be >= 1");
  ring_.assign(64, 0);
}

void MemoryController::Reset() {
  base_word_ = 0;
  head_ = 0;
  std::fill(ring_.begin(), ring_.end(), 0);
  lines_ = 0;
  queue_cycles_ = 0;
}

void MemoryController::Grow(size_t words_needed) {
  size_t n = ring_.size();
  while (n < words_needed) n *= 2;
  std::vector<uint64_t> grown(n, 0);
  for (size_t i = 0; i < ring_.size(); ++i) grown[i] = ring_[(head_ + i) & (ring_.size() - 1)];
  ring_ = std::move(grown);
  head_ = 0;
}

uint64_t MemoryController::ServeLine(uint64_t arrival) {
  uint64_t slot = (arrival + line_cycles_ - 1) / line_cycles_;
  if (slot < base_word_ * 64) slot = base_word_ * 64;  // (the floor guarantees this is rare)
  for (;;) {
    const uint64_t w = slot / 64 - base_word_;
    if (w >= ring_.size()) Grow(w + 1);
    uint64_t& word = ring_[(head_ + w) & (ring_.size() - 1)];
    const uint64_t free_bits = ~word & (~uint64_t{0} << (slot & 63));
    if (free_bits != 0) {
      const int bit = __builtin_ctzll(free_bits);
      word |= uint64_t{1} << bit;
      const uint64_t start = ((base_word_ + w) * 64 + uint64_t(bit)) * line_cycles_;
      ++lines_;
      queue_cycles_ += start > arrival ? start - arrival : 0;
      return start + line_cycles_;
    }
    slot = (slot / 64 + 1) * 64;
  }
}

void MemoryController::AdvanceFloor(uint64_t t) {
  const uint64_t word = t / line_cycles_ / 64;
  while (base_word_ < word) {
    ring_[head_] = 0;
    head_ = (head_ + 1) & (ring_.size() - 1);
    ++base_word_;
  }
}

// ------------------------------------------------------------------------------------------
// Mfc

void MfcStats::Merge(const MfcStats& o) {
  commands += o.commands;
  gets += o.gets;
  puts += o.puts;
  list_elements += o.list_elements;
  bytes += o.bytes;
  lines += o.lines;
  queue_full_stalls += o.queue_full_stalls;
}

Mfc::Mfc(int spe, LocalStore& ls, const MainMemory& memory, MemoryController& mic, SpuClock& clock,
         const MemoryTiming& timing)
    : spe_(spe), ls_(ls), memory_(memory), mic_(mic), clock_(clock), timing_(timing) {
  bus_free_.assign(static_cast<size_t>(std::max(1, timing.mfc_bus_slots)), 0);
}

void Mfc::Reset() {
  commands_.clear();
  pieces_.clear();
  std::fill(bus_free_.begin(), bus_free_.end(), 0);
  std::fill(std::begin(barrier_until_), std::end(barrier_until_), 0);
  stats_ = MfcStats{};
}

std::string Mfc::Op(const char* name, Lsa ls, Ea ea, uint32_t size, uint32_t tag) const {
  return "SPE " + std::to_string(spe_) + " " + name + "(ls " + Hex(ls) + ", ea " + Hex(ea) +
         ", size " + std::to_string(size) + ", tag " + std::to_string(tag) + ")";
}

void Mfc::CheckTag(const std::string& op, uint32_t tag) const {
  if (tag >= kNumTags) {
    throw Error(op + ": tag " + std::to_string(tag) + " is out of range (tags are 0..31)");
  }
}

void Mfc::CheckTransfer(const std::string& op, Lsa ls, Ea ea, uint32_t size, bool list_element) {
  const bool small = size == 1 || size == 2 || size == 4 || size == 8;
  if (!small && (size == 0 || size % 16 != 0 || size > kMaxDmaSize)) {
    throw Error(op + ": illegal DMA size " + std::to_string(size) +
                " (must be 1, 2, 4, 8 or a multiple of 16 up to 16384)");
  }
  if ((ls & 15u) != (ea & 15u)) {
    throw Error(op + ": local-store address " + Hex(ls) + " and effective address " + Hex(ea) +
                " differ in their low 4 bits");
  }
  if (small && (ea % size != 0)) {
    throw Error(op + ": a " + std::to_string(size) + "-byte DMA must be naturally aligned (ea " +
                Hex(ea) + ")");
  }
  if (!small && (ea & 15u) != 0) {
    throw Error(op + ": a DMA of " + std::to_string(size) + " bytes must be 16-byte aligned (ea " +
                Hex(ea) + ")");
  }
  if (!ls_.Contains(ls, size)) {
    throw Error(op + ": local-store range [" + Hex(ls) + ", +" + std::to_string(size) +
                ") runs past the " + std::to_string(ls_.size()) + "-byte local store");
  }
  (void)list_element;
}

void Mfc::Issue(Kind kind, Order order, Lsa ls, Ea ea, uint32_t size, uint32_t tag) {
  const char* names[2][3] = {{"MfcGet", "MfcGetf", "MfcGetb"}, {"MfcPut", "MfcPutf", "MfcPutb"}};
  // Build the description only when a check fails (hot path).
  auto op = [&] { return Op(names[kind][order], ls, ea, size, tag); };
  if (tag >= kNumTags) CheckTag(op(), tag);
  const bool small = size == 1 || size == 2 || size == 4 || size == 8;
  if (!(small || (size != 0 && size % 16 == 0 && size <= kMaxDmaSize)) ||
      (ls & 15u) != (ea & 15u) || (small && ea % size != 0) || (!small && (ea & 15u) != 0) ||
      !ls_.Contains(ls, size)) {
    CheckTransfer(op(), ls, ea, size, false);
  }
  uint8_t* host = memory_.Find(ea, size, kind == kPut);
  if (host == nullptr) host = memory_.Check(ea, size, kind == kPut, op());
  if (kind == kPut) {
    std::memcpy(host, ls_.Bytes(ls, size), size);
  } else {
    std::memset(ls_.Bytes(ls, size), kPoison, size);
  }
  clock_.Charge(Cost::kDma, timing_.dma_issue_cycles);
  const uint32_t first = static_cast<uint32_t>(pieces_.size());
  pieces_.push_back(Piece{ls, ea, size, host});
  Schedule(kind, order, tag, first, 1);
}

void Mfc::MfcGet(Lsa ls, Ea ea, uint32_t size, uint32_t tag) {
  Issue(kGet, kPlain, ls, ea, size, tag);
}
void Mfc::MfcPut(Lsa ls, Ea ea, uint32_t size, uint32_t tag) {
  Issue(kPut, kPlain, ls, ea, size, tag);
}
void Mfc::MfcGetf(Lsa ls, Ea ea, uint32_t size, uint32_t tag) {
  Issue(kGet, kFence, ls, ea, size, tag);
}
void Mfc::MfcPutf(Lsa ls, Ea ea, uint32_t size, uint32_t tag) {
  Issue(kPut, kFence, ls, ea, size, tag);
}
void Mfc::MfcGetb(Lsa ls, Ea ea, uint32_t size, uint32_t tag) {
  Issue(kGet, kBarrier, ls, ea, size, tag);
}
void Mfc::MfcPutb(Lsa ls, Ea ea, uint32_t size, uint32_t tag) {
  Issue(kPut, kBarrier, ls, ea, size, tag);
}

void Mfc::MfcGetList(Lsa ls, uint32_t ea_high, Lsa list, uint32_t list_bytes, uint32_t tag) {
  IssueList(kGet, ls, ea_high, list, list_bytes, tag);
}
void Mfc::MfcPutList(Lsa ls, uint32_t ea_high, Lsa list, uint32_t list_bytes, uint32_t tag) {
  IssueList(kPut, ls, ea_high, list, list_bytes, tag);
}

void Mfc::IssueList(Kind kind, Lsa ls, uint32_t ea_high, Lsa list, uint32_t list_bytes,
                    uint32_t tag) {
  const std::string op = "SPE " + std::to_string(spe_) +
                         (kind == kGet ? " MfcGetList" : " MfcPutList") + "(ls " + Hex(ls) +
                         ", list " + Hex(list) + ", " + std::to_string(list_bytes) + " B, tag " +
                         std::to_string(tag) + ")";
  CheckTag(op, tag);
  if (list_bytes == 0 || list_bytes % 8 != 0 || list_bytes / 8 > kMaxDmaListElements) {
    throw Error(op + ": list size must be a multiple of 8 bytes holding 1 to 2048 elements");
  }
  if (list % 8 != 0) throw Error(op + ": the list must be 8-byte aligned in local store");
  const DmaListElement* elements = ls_.As<const DmaListElement>(list, list_bytes / 8);
  const uint32_t n = list_bytes / 8;
  const uint32_t first = static_cast<uint32_t>(pieces_.size());
  Lsa at = ls;
  for (uint32_t i = 0; i < n; ++i) {
    const DmaListElement e = elements[i];
    const std::string elem = op + " element " + std::to_string(i);
    if ((e.size & 0x80000000u) != 0) {
      throw Error(elem + ": stall-and-notify elements are not supported");
    }
    if (e.size > kMaxDmaSize) {
      throw Error(elem + ": element size " + std::to_string(e.size) + " exceeds 16384 bytes");
    }
    const Ea ea = (Ea{ea_high} << 32) | e.eal;
    CheckTransfer(elem, at, ea, e.size, true);
    uint8_t* host = memory_.Check(ea, e.size, kind == kPut, elem);
    if (kind == kPut) {
      std::memcpy(host, ls_.Bytes(at, e.size), e.size);
    } else {
      std::memset(ls_.Bytes(at, e.size), kPoison, e.size);
    }
    pieces_.push_back(Piece{at, ea, e.size, host});
    at += e.size;
  }
  clock_.Charge(Cost::kDma, timing_.dma_issue_cycles);
  stats_.list_elements += n;
  Schedule(kind, kPlain, tag, first, n);
}

int Mfc::QueueOccupancy() const {
  int busy = 0;
  for (const Command& c : commands_) busy += c.done > clock_.now() ? 1 : 0;
  return busy;
}

void Mfc::Schedule(Kind kind, Order order, uint32_t tag, uint32_t first_piece,
                   uint32_t num_pieces) {
  // A full queue (16 commands not yet complete) stalls the SPU until the oldest completes.
  for (;;) {
    int busy = 0;
    uint64_t earliest = ~uint64_t{0};
    for (const Command& c : commands_) {
      if (c.done > clock_.now()) {
        ++busy;
        earliest = std::min(earliest, c.done);
      }
    }
    if (busy < timing_.mfc_queue_depth) break;
    ++stats_.queue_full_stalls;
    clock_.WaitUntil(Cost::kDma, earliest);
  }
  uint64_t start = clock_.now();
  start = std::max(start, barrier_until_[tag]);
  if (order != kPlain) {
    for (const Command& c : commands_) {
      if (c.tag == tag) start = std::max(start, c.done);
    }
  }
  auto slot = std::min_element(bus_free_.begin(), bus_free_.end());
  start = std::max(start, *slot);
  uint64_t arrival = start;
  uint64_t last_end = start;
  uint64_t bytes = 0, lines = 0;
  for (uint32_t i = 0; i < num_pieces; ++i) {
    const Piece& p = pieces_[first_piece + i];
    if (num_pieces > 1) arrival += timing_.dma_list_element_cycles;
    const uint64_t n = LinesTouched(p.ea, p.size);
    for (uint64_t k = 0; k < n; ++k) {
      last_end = std::max(last_end, mic_.ServeLine(arrival));
      arrival += mic_.line_cycles();  // the SPE's port moves 8 B/cycle
    }
    bytes += p.size;
    lines += n;
  }
  Command c;
  c.done = last_end + timing_.dma_latency_cycles;
  c.tag = tag;
  c.kind = kind;
  c.first_piece = first_piece;
  c.num_pieces = num_pieces;
  *slot = c.done;
  if (order == kBarrier) barrier_until_[tag] = std::max(barrier_until_[tag], c.done);
  commands_.push_back(c);
  ++stats_.commands;
  (kind == kGet ? stats_.gets : stats_.puts) += 1;
  stats_.bytes += bytes;
  stats_.lines += lines;
}

void Mfc::Land(const Command& c) {
  if (c.kind != kGet) return;
  for (uint32_t i = 0; i < c.num_pieces; ++i) {
    const Piece& p = pieces_[c.first_piece + i];
    std::memcpy(ls_.Bytes(p.ls, p.size), p.host, p.size);
  }
}

void Mfc::WaitTagsAll(uint32_t mask) {
  uint64_t until = clock_.now();
  for (const Command& c : commands_) {
    if ((mask >> c.tag) & 1u) until = std::max(until, c.done);
  }
  // The status read blocks until the data is there, then takes its channel latency.
  clock_.WaitUntil(Cost::kDma, until);
  clock_.Charge(Cost::kDma, timing_.dma_wait_cycles);
  // Retire in issue order so a later get into the same buffer wins.
  size_t kept = 0;
  for (size_t i = 0; i < commands_.size(); ++i) {
    const Command& c = commands_[i];
    if ((mask >> c.tag) & 1u) {
      Land(c);
    } else {
      commands_[kept++] = c;
    }
  }
  commands_.resize(kept);
  if (commands_.empty()) {
    pieces_.clear();
  } else if (pieces_.size() > 4096) {  // compact: keep only the pieces still referenced
    std::vector<Piece> live;
    for (Command& c : commands_) {
      const uint32_t first = static_cast<uint32_t>(live.size());
      live.insert(live.end(), pieces_.begin() + c.first_piece,
                  pieces_.begin() + c.first_piece + c.num_pieces);
      c.first_piece = first;
    }
    pieces_ = std::move(live);
  }
}

// ------------------------------------------------------------------------------------------
// AtomicUnit

void AtomicStats::Merge(const AtomicStats& o) {
  getllar += o.getllar;
  cache_hits += o.cache_hits;
  putllc_ok += o.putllc_ok;
  putllc_failed += o.putllc_failed;
  putlluc += o.putlluc;
}

AtomicUnit::AtomicUnit(int spe, LocalStore& ls, const MainMemory& memory, MemoryController& mic,
                       AtomicMemory& atomic_memory, SpuClock& clock, const MemoryTiming& timing)
    : spe_(spe),
      ls_(ls),
      memory_(memory),
      mic_(mic),
      atomic_memory_(atomic_memory),
      clock_(clock),
      timing_(timing) {
  cache_.resize(static_cast<size_t>(std::max(0, timing.atomic_cache_lines)));
}

void AtomicUnit::Reset() {
  pending_ = false;
  done_ = 0;
  status_ = 0;
  reserved_ = false;
  for (CacheLine& l : cache_) l = CacheLine{};
  use_counter_ = 0;
  stats_ = AtomicStats{};
}

uint8_t* AtomicUnit::Begin(const char* op, Lsa ls, Ea ea) {
  const bool write = std::strcmp(op, "getllar") != 0;
  uint8_t* host = ls % kAtomicLine == 0 && ea % kAtomicLine == 0 && ls_.Contains(ls, kAtomicLine)
                      ? memory_.Find(ea, kAtomicLine, write)
                      : nullptr;
  if (host == nullptr) {
    const std::string what =
        "SPE " + std::to_string(spe_) + " " + op + "(ls " + Hex(ls) + ", ea " + Hex(ea) + ")";
    if (ls % kAtomicLine != 0 || ea % kAtomicLine != 0) {
      throw Error(what +
                  ": atomic commands need 128-byte aligned local-store and effective "
                  "addresses");
    }
    if (!ls_.Contains(ls, kAtomicLine)) throw Error(what + ": line runs past the local store");
    host = memory_.Check(ea, kAtomicLine, write, what);
  }
  // One atomic command at a time: a second issue waits for the first to complete.
  if (pending_) {
    clock_.WaitUntil(Cost::kAtomic, done_);
    pending_ = false;
  }
  clock_.Charge(Cost::kAtomic, timing_.atomic_issue_cycles);
  return host;
}

bool AtomicUnit::CacheAccess(Ea line, uint64_t version) {
  ++use_counter_;
  CacheLine* victim = nullptr;
  for (CacheLine& l : cache_) {
    if (l.valid && l.line == line) {
      l.last_use = use_counter_;
      if (l.version == version) return true;
      l.version = version;  // stale copy: refetched
      return false;
    }
    if (victim == nullptr || !l.valid || (victim->valid && l.last_use < victim->last_use)) {
      victim = &l;
    }
  }
  if (victim != nullptr) *victim = CacheLine{line, version, use_counter_, true};
  return false;
}

void AtomicUnit::Getllar(Lsa ls, Ea ea) {
  const uint8_t* host = Begin("getllar", ls, ea);
  ++stats_.getllar;
  const uint64_t version = atomic_memory_.Version(ea);
  std::memcpy(ls_.Bytes(ls, kAtomicLine), host, kAtomicLine);
  reserved_ = true;
  reserved_line_ = ea;
  reserved_version_ = version;
  if (CacheAccess(ea, version)) {
    ++stats_.cache_hits;
    done_ = clock_.now() + timing_.atomic_hit_cycles;
  } else {
    done_ = mic_.ServeLine(clock_.now()) + timing_.atomic_latency_cycles;
  }
  status_ = kGetllarDone;
  pending_ = true;
}

void AtomicUnit::Putllc(Lsa ls, Ea ea) {
  uint8_t* host = Begin("putllc", ls, ea);
  const uint64_t version = atomic_memory_.Version(ea);
  const bool ok = reserved_ && reserved_line_ == ea && reserved_version_ == version;
  reserved_ = false;
  if (ok) {
    std::memcpy(host, ls_.Bytes(ls, kAtomicLine), kAtomicLine);
    const uint64_t v = atomic_memory_.Bump(ea);
    // The line is in this SPE's atomic cache (getllar put it there): the store is local.
    CacheAccess(ea, v);
    ++stats_.putllc_ok;
    status_ = 0;
  } else {
    ++stats_.putllc_failed;
    status_ = kPutllcFailed;
  }
  done_ = clock_.now() + timing_.atomic_hit_cycles;
  pending_ = true;
}

void AtomicUnit::Putlluc(Lsa ls, Ea ea) {
  uint8_t* host = Begin("putlluc", ls, ea);
  const bool hit = CacheAccess(ea, atomic_memory_.Version(ea));
  std::memcpy(host, ls_.Bytes(ls, kAtomicLine), kAtomicLine);
  const uint64_t v = atomic_memory_.Bump(ea);
  CacheAccess(ea, v);
  if (reserved_ && reserved_line_ == ea) reserved_ = false;
  ++stats_.putlluc;
  done_ = hit ? clock_.now() + timing_.atomic_hit_cycles
              : mic_.ServeLine(clock_.now()) + timing_.atomic_latency_cycles;
  status_ = kPutllucDone;
  pending_ = true;
}

uint32_t AtomicUnit::ReadStatus() {
  if (!pending_) {
    clock_.Charge(Cost::kAtomic, timing_.atomic_status_cycles);
    return 0;
  }
  clock_.WaitUntil(Cost::kAtomic, done_);
  clock_.Charge(Cost::kAtomic, timing_.atomic_status_cycles);
  pending_ = false;
  return status_;
}

}  // namespace rs::sim
