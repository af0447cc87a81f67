// Simulated memory flow controller (MFC) of an SPE, the shared memory interface controller (MIC)
// and the atomic unit. Names mirror spu_mfcio.h: MfcGet / MfcPut (ls, ea, size, tag), the list
// forms, WaitTagsAll, getllar / putllc / putlluc. Data really moves between the host arrays that
// stand for main memory and the SPE's local store; time is charged to the SPU's clock.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <unordered_map>
#include <vector>

#include "sim/config.h"
#include "sim/local_store.h"

namespace rs::sim {

// A simulated effective address: a byte address in the simulated 64-bit main memory, never a
// host pointer. MainMemory places every registered host array at an EA of its own (see there),
// so everything that depends on addresses (software-cache sets, 128-B line counts, atomic lines,
// DMA-list high words) is the same in every process, whatever the host allocator returns.
using Ea = uint64_t;

inline constexpr uint32_t kMaxDmaSize = 16384;         // MFC_MAX_DMA_SIZE
inline constexpr uint32_t kMaxDmaListElements = 2048;  // MFC_MAX_DMA_LIST_SIZE
inline constexpr uint32_t kNumTags = 32;
inline constexpr uint32_t kAtomicLine = 128;

// Where an SPU's cycles went. Every cycle of an SPE's clock is in exactly one bucket:
// compute (the annotated cost model), DMA (issuing MFC commands, waiting for tag groups and for a
// full command queue), atomic (getllar/putllc issue and status waits, tile-counter retries),
// cache (software-cache lookups and their miss DMAs), idle (after the SPE's last ray until the
// frame's last SPE finishes).
enum class Cost : int { kCompute = 0, kDma = 1, kAtomic = 2, kCache = 3, kIdle = 4 };
inline constexpr int kNumCosts = 5;
const char* CostName(Cost c);

struct CycleBreakdown {
  uint64_t cycles[kNumCosts] = {};
  uint64_t& operator[](Cost c) { return cycles[static_cast<int>(c)]; }
  uint64_t operator[](Cost c) const { return cycles[static_cast<int>(c)]; }
  uint64_t Total() const;
  void Merge(const CycleBreakdown& o);
};

// The SPU's clock (cycles) and the breakdown of the cycles spent so far.
class SpuClock {
 public:
  uint64_t now() const { return now_; }
  const CycleBreakdown& spent() const { return spent_; }
  // Advances by `cycles` charged to `c` (or to the redirect category, see Redirect).
  void Charge(Cost c, uint64_t cycles);
  // Advances to `t` if it lies ahead, charging the gap to `c`.
  void WaitUntil(Cost c, uint64_t t) {
    if (t > now_) Charge(c, t - now_);
  }
  // While a redirect is active every charge goes to `c` (the software cache charges its DMA and
  // waits as cache time). Returns the previous redirect (-1 for none).
  int Redirect(int c) {
    const int old = redirect_;
    redirect_ = c;
    return old;
  }
  void Reset() {
    now_ = 0;
    spent_ = CycleBreakdown{};
    redirect_ = -1;
  }

 private:
  uint64_t now_ = 0;
  CycleBreakdown spent_;
  int redirect_ = -1;
};

// The host arrays that stand for main memory, each mapped at its own simulated EA range. Every
// DMA's effective-address range must lie inside one registered region (writable for puts), else
// the DMA is illegal (rs::Error). Regions start on kRegionAlign boundaries: Register places a
// region at the first such boundary above every region so far, starting at kMainMemoryBase, so
// the EAs depend only on the order and sizes of the registrations (deterministic, like a PPE
// program laying out its arrays); RegisterAt places one at an EA chosen by the caller (a
// layout planned ahead, e.g. CellImage). EA 0 is never valid.
class MainMemory {
 public:
  static constexpr Ea kMainMemoryBase = 0x10000000;  // 256 MiB: PS3 user memory starts higher
  static constexpr Ea kRegionAlign = 4096;           // a page, as a PPE allocator hands them out

  // Returns the region's EA. Throws rs::Error if it would overlap a registered region. A
  // region of 0 bytes is not registered (returns the EA it would have had).
  Ea Register(const void* data, size_t bytes, std::string name, bool writable = false);
  // The same at `ea` (a multiple of 128).
  Ea RegisterAt(Ea ea, const void* data, size_t bytes, std::string name, bool writable = false);
  // The EA the next Register call would use (for a region laid out by RegisterAt after it).
  Ea NextEa() const;
  void Clear() { regions_.clear(); }
  // Host pointer for [ea, ea + bytes); throws rs::Error naming `op` if no registered region
  // holds the whole range, or `write` and the region is read-only.
  uint8_t* Check(Ea ea, uint64_t bytes, bool write, const std::string& op) const;
  // The same test without the message: nullptr if the access is illegal.
  uint8_t* Find(Ea ea, uint64_t bytes, bool write) const;
  size_t num_regions() const { return regions_.size(); }

 private:
  struct Region {
    Ea begin = 0;
    Ea end = 0;
    uint8_t* host = nullptr;
    std::string name;
    bool writable = false;
  };
  const Region* Lookup(Ea ea, uint64_t bytes) const;
  std::vector<Region> regions_;  // sorted by begin, disjoint
};

// The MIC: one server for 128-B lines shared by all SPEs, mic_line_cycles per line, each line
// served in the first free slot at or after its arrival (slots are aligned to mic_line_cycles).
// Arrivals must not precede the floor (the earliest SPE clock, set by the scheduler).
class MemoryController {
 public:
  explicit MemoryController(uint32_t line_cycles = 16);
  // Serves one line arriving at `arrival`; returns the cycle its transfer ends.
  uint64_t ServeLine(uint64_t arrival);
  // No arrival will come before `t` any more: forget older slots.
  void AdvanceFloor(uint64_t t);
  void Reset();

  uint64_t lines() const { return lines_; }
  uint64_t queue_cycles() const { return queue_cycles_; }  // sum of (start - arrival)
  uint32_t line_cycles() const { return line_cycles_; }

 private:
  void Grow(size_t words_needed);

  uint32_t line_cycles_;
  uint64_t base_word_ = 0;      // slot index / 64 of ring_[head_]
  size_t head_ = 0;             // ring index of base_word_
  std::vector<uint64_t> ring_;  // bit s of word w: slot (base_word_ + w') * 64 + s is busy
  uint64_t lines_ = 0;
  uint64_t queue_cycles_ = 0;
};

// One element of a DMA list in local store (spu_mfcio.h mfc_list_element: notify/stall bit,
// 15-bit size, 32-bit low EA; the high EA word comes with the command).
struct DmaListElement {
  uint32_t size;  // bit 31 = stall-and-notify (not supported here: must be 0)
  uint32_t eal;
};
static_assert(sizeof(DmaListElement) == 8);

struct MfcStats {
  uint64_t commands = 0;
  uint64_t gets = 0;
  uint64_t puts = 0;
  uint64_t list_elements = 0;
  uint64_t bytes = 0;
  uint64_t lines = 0;
  uint64_t queue_full_stalls = 0;
  void Merge(const MfcStats& o);
};

// The MFC of one SPE: a 16-entry command queue, 32 tag groups, DMA lists, fences and barriers.
// Timing: an issue costs dma_issue_cycles of SPU time; a command starts when one of the SPE's
// mfc_bus_slots is free (and after earlier commands of its tag, for fence / barrier forms); its
// 128-B lines (partial lines cost a whole line) reach the MIC one per mic_line_cycles; it
// completes dma_latency_cycles after its last line was served. Gets: the destination is
// filled with a poison pattern at issue and receives the data when the SPU waits on the tag
// (WaitTagsAll), so reading a buffer before waiting for it shows up as garbage. Puts copy the LS
// data to main memory at issue. Illegal commands (size, alignment, tag, ranges, list format)
// throw rs::Error naming the SPE, the command and the rule.
class Mfc {
 public:
  Mfc(int spe, LocalStore& ls, const MainMemory& memory, MemoryController& mic, SpuClock& clock,
      const MemoryTiming& timing);

  void MfcGet(Lsa ls, Ea ea, uint32_t size, uint32_t tag);
  void MfcPut(Lsa ls, Ea ea, uint32_t size, uint32_t tag);
  // Fence (f): starts after all earlier commands of the same tag. Barrier (b): also holds all
  // later commands of the tag until it completes.
  void MfcGetf(Lsa ls, Ea ea, uint32_t size, uint32_t tag);
  void MfcPutf(Lsa ls, Ea ea, uint32_t size, uint32_t tag);
  void MfcGetb(Lsa ls, Ea ea, uint32_t size, uint32_t tag);
  void MfcPutb(Lsa ls, Ea ea, uint32_t size, uint32_t tag);
  // List forms: the list (list_bytes / 8 DmaListElements, 8-B aligned in LS, at most 2048) is
  // read from LS at issue; element i moves size_i bytes between ls (advanced by each element's
  // size) and (ea_high << 32) | eal_i. One queue entry for the whole list.
  void MfcGetList(Lsa ls, uint32_t ea_high, Lsa list, uint32_t list_bytes, uint32_t tag);
  void MfcPutList(Lsa ls, uint32_t ea_high, Lsa list, uint32_t list_bytes, uint32_t tag);

  // mfc_write_tag_mask + mfc_read_tag_status_all: the SPU waits until every command of the
  // tags in `mask` has completed (charged as DMA time beyond dma_wait_cycles); their data lands.
  void WaitTagsAll(uint32_t mask);
  // Waits for every outstanding command.
  void WaitAll() { WaitTagsAll(0xFFFFFFFFu); }

  // Commands issued and not yet retired by a wait (completed or not), for tests.
  size_t outstanding() const { return commands_.size(); }
  // Queue entries busy at the SPU's current time.
  int QueueOccupancy() const;
  const MfcStats& stats() const { return stats_; }
  void Reset();  // drops outstanding commands (no data lands), clears stats

 private:
  enum Kind : int { kGet = 0, kPut = 1 };
  enum Order : int { kPlain = 0, kFence = 1, kBarrier = 2 };
  struct Piece {
    Lsa ls;
    Ea ea;
    uint32_t size;
    const uint8_t* host;  // main-memory bytes of [ea, ea + size) (gets land from here)
  };
  struct Command {
    uint64_t done = 0;
    uint32_t tag = 0;
    Kind kind = kGet;
    uint32_t first_piece = 0;  // pieces_[first_piece, first_piece + num_pieces)
    uint32_t num_pieces = 0;
  };

  void Issue(Kind kind, Order order, Lsa ls, Ea ea, uint32_t size, uint32_t tag);
  void IssueList(Kind kind, Lsa ls, uint32_t ea_high, Lsa list, uint32_t list_bytes, uint32_t tag);
  void CheckTransfer(const std::string& op, Lsa ls, Ea ea, uint32_t size, bool list_element);
  void CheckTag(const std::string& op, uint32_t tag) const;
  // Queue-full stall, bus slot, MIC lines; appends the command. pieces_ tail holds its pieces.
  void Schedule(Kind kind, Order order, uint32_t tag, uint32_t first_piece, uint32_t num_pieces);
  void Land(const Command& c);  // copies a get's data into LS
  std::string Op(const char* name, Lsa ls, Ea ea, uint32_t size, uint32_t tag) const;

  int spe_;
  LocalStore& ls_;
  const MainMemory& memory_;
  MemoryController& mic_;
  SpuClock& clock_;
  const MemoryTiming& timing_;
  std::vector<Command> commands_;  // issued, not yet retired by a wait, in issue order
  std::vector<Piece> pieces_;
  std::vector<uint64_t> bus_free_;  // per bus slot: cycle it becomes free
  uint64_t barrier_until_[kNumTags] = {};
  MfcStats stats_;
};

// Version counters of the 128-B lines (by EA) written through the atomic unit (shared by all
// SPEs). A line never written has version 0.
class AtomicMemory {
 public:
  uint64_t Version(Ea line) const {
    const auto it = versions_.find(line);
    return it == versions_.end() ? 0 : it->second;
  }
  uint64_t Bump(Ea line) { return ++versions_[line]; }
  void Reset() { versions_.clear(); }

 private:
  std::unordered_map<Ea, uint64_t> versions_;
};

struct AtomicStats {
  uint64_t getllar = 0;
  uint64_t cache_hits = 0;  // getllar served by the atomic cache
  uint64_t putllc_ok = 0;
  uint64_t putllc_failed = 0;  // reservation lost: the retries of a lock-free update
  uint64_t putlluc = 0;
  void Merge(const AtomicStats& o);
};

// spu_mfcio.h status bits returned by mfc_read_atomic_status().
inline constexpr uint32_t kPutllcFailed = 1;  // MFC_PUTLLC_STATUS
inline constexpr uint32_t kPutllucDone = 2;   // MFC_PUTLLUC_STATUS
inline constexpr uint32_t kGetllarDone = 4;   // MFC_GETLLAR_STATUS

// The atomic unit of one SPE: one command at a time (issuing while one is pending waits for it),
// a reservation per SPE, and a 4-line atomic cache. getllar copies the line into LS (both
// 128-B aligned) and reserves it; putllc stores the LS line only if no other SPE stored to it
// since this SPE's getllar (version counter), else reports kPutllcFailed. Lines that hit the
// atomic cache (present, version unchanged) take atomic_hit_cycles; misses pay a MIC line and
// atomic_latency_cycles. The caller must run when its SPE is the earliest in simulated time
// (the scheduler guarantees it at the steps that use the atomic unit) for contention to be
// exact.
class AtomicUnit {
 public:
  AtomicUnit(int spe, LocalStore& ls, const MainMemory& memory, MemoryController& mic,
             AtomicMemory& atomic_memory, SpuClock& clock, const MemoryTiming& timing);

  void Getllar(Lsa ls, Ea ea);
  void Putllc(Lsa ls, Ea ea);
  void Putlluc(Lsa ls, Ea ea);
  // mfc_read_atomic_status(): waits for the pending command (charged as atomic time) and
  // returns its status bits (0 if none was pending).
  uint32_t ReadStatus();
  bool pending() const { return pending_; }
  const AtomicStats& stats() const { return stats_; }
  void Reset();

 private:
  // Checks the command, waits for a pending one, charges the issue; returns the line's host bytes.
  uint8_t* Begin(const char* op, Lsa ls, Ea ea);
  // Atomic-cache lookup; true on a hit. Inserts (LRU) on a miss.
  bool CacheAccess(Ea line, uint64_t version);

  int spe_;
  LocalStore& ls_;
  const MainMemory& memory_;
  MemoryController& mic_;
  AtomicMemory& atomic_memory_;
  SpuClock& clock_;
  const MemoryTiming& timing_;
  bool pending_ = false;
  uint64_t done_ = 0;
  uint32_t status_ = 0;
  bool reserved_ = false;
  Ea reserved_line_ = 0;
  uint64_t reserved_version_ = 0;
  struct CacheLine {
    Ea line = 0;
    uint64_t version = 0;
    uint64_t last_use = 0;
    bool valid = false;
  };
  std::vector<CacheLine> cache_;
  uint64_t use_counter_ = 0;
  AtomicStats stats_;
};

}  // namespace rs::sim
