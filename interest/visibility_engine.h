// interest/visibility_engine.h: the interest step as one engine call: per observer, the visible set with enter and leave events
// and hysteresis. Two implementations: the host reference (host_visibility_engine.h: any
// pair_finder, then the diff on the host) and the GPU's (gpu/visibility.h: candidates and
// classification where the engine runs, only the sets and events come back). The contract is the
// interest tracker's (docs/zone.md, "Interest tracker"); interest_tracker runs every update on an
// engine (the one set, or its own host reference). Plain arrays only, so that the GPU layer can
// implement it without knowing the tracker's types.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <span>

namespace zone::interest {

/// One update's rows (observers and targets alike: every entity is both). Arrays of n entries,
/// except the float arrays (3n: x, y, z per row).
struct visibility_input {
  std::size_t n = 0;
  /// Entity handles. Their low `slot_bits` bits (the slot) are pairwise distinct among the rows;
  /// a row's previous row is the row with the same handle in the previous update.
  const std::uint32_t* ids = nullptr;
  std::uint32_t slot_bits = 20;
  /// One past the highest slot among ids (sizes per-slot tables); 0: the engine finds it.
  std::size_t slot_count = 0;
  const float* position = nullptr;            ///< centre
  const float* aoi_half = nullptr;            ///< AOI half-extents (>= 0)
  const float* body_half = nullptr;           ///< presence half-extents (>= 0)
  const std::uint32_t* visibility = nullptr;  ///< the presence box's class bits
  const std::uint32_t* sees = nullptr;        ///< classes the AOI sees (0: sees nothing)
  /// Rows whose visible set the caller reads on the host right after the update (n entries,
  /// non-zero = wanted); the others' sets stay on the device until fetch_all_visible(). Null:
  /// every row. Enters and leaves always come back whole.
  const std::uint8_t* wanted = nullptr;
  float hysteresis = 0;  ///< margin h >= 0
  /// Keep at most this many entities per observer, the closest (0: no cap; see docs/zone.md).
  /// Only for an engine whose caps_visible() is true.
  std::uint32_t max_visible = 0;
  /// Identifies ids, aoi_half, body_half, visibility and sees (0: unknown). When it equals the
  /// previous call's (and n too), the engine may keep those columns from that call and take only
  /// the positions (and wanted): the caller promises they did not change.
  std::uint64_t static_version = 0;
  /// Called once the device work is under way, before the engine waits for it: host work that
  /// needs none of the result runs in the device's shadow. May be empty. An engine without a
  /// device (host_visibility_engine) does not call it: the caller does that work after update().
  std::function<void()> while_waiting;
};

/// Where the time of the last update went (host wall clock, and device events where the engine
/// has a device). An engine fills the phases it has and leaves the others 0.
struct visibility_timing {
  // A host engine (host_visibility_engine.h): boxes, the pair finder, the diff.
  double boxes_ms = 0;    ///< boxes built (AOI grown by h, presence)
  double find_ms = 0;     ///< the pair finder
  double diff_ms = 0;     ///< pairs into per-observer sets and events, of which:
  double count_ms = 0;    ///<   candidates counted per row
  double offsets_ms = 0;  ///<   row offsets
  double fill_ms = 0;     ///<   candidates filled into their rows
  double rows_ms = 0;     ///<   per row: classified, merged with the previous set (and capped)
  // A device engine (gpu/visibility.h):
  double pack_ms = 0;      ///< host: inputs into the engine's staging memory
  double upload_ms = 0;    ///< host-to-device copy
  double device_ms = 0;    ///< grid, candidates, classification (device time), of which:
  double grid_ms = 0;      ///<   boxes, plan, the grid over the presence boxes
  double query_ms = 0;     ///<   candidates, each classified (stay or enter) as it is found
  double place_ms = 0;     ///<   scans of the list sizes, enters placed in their rows
  double write_ms = 0;     ///<   sorted lists written (and the rows copied back gathered)
  double download_ms = 0;  ///< device-to-host copy of the sets and events
  /// host: blocked on the device after the caller's while_waiting work (the first pass's wait;
  /// near 0: that work outlasted the device, so it lengthened the update)
  double wait_ms = 0;
  double total_ms = 0;     ///< wall time of the whole update (every engine)
  std::uint32_t reruns = 0;  ///< device passes redone after a buffer grew
};

/// Compact CSR lists: row r's entries are data[off[r], off[r + 1]) (off has rows + 1 entries).
struct visibility_lists {
  const std::uint32_t* data = nullptr;
  const std::uint32_t* off = nullptr;
};

/// The result of an update, valid until the engine's next update or load_previous. Row r of a
/// list is [off[r], off[r] + len[r]) of its array where the list has a `len` array, else (compact
/// CSR) [off[r], off[r + 1]) (off has n + 1 entries); visible sets, enters and leaves are each
/// sorted ascending by handle. With
/// visibility_input::wanted, `visible` holds the wanted rows' sets only (the others are empty
/// there: visible_complete is false) and fetch_all_visible() brings every row's.
struct visibility_output {
  const std::uint32_t* visible = nullptr;
  const std::uint32_t* visible_off = nullptr;
  const std::uint32_t* enters = nullptr;
  const std::uint32_t* enter_off = nullptr;
  const std::uint32_t* leaves = nullptr;
  const std::uint32_t* leave_off = nullptr;
  /// Row lengths (null: compact, the length is off[r + 1] - off[r]).
  const std::uint32_t* visible_len = nullptr;
  const std::uint32_t* enter_len = nullptr;
  const std::uint32_t* leave_len = nullptr;
  bool visible_complete = true;
  std::uint64_t visible_total = 0;  ///< entries of every row's visible set (also when not complete)
  std::uint64_t pairs = 0;       ///< qualifying (AOI grown by h, presence) pairs, self pairs included
  std::uint64_t candidates = 0;  ///< the same without self pairs
  std::uint64_t capped = 0;      ///< entities dropped by visibility_input::max_visible
  visibility_timing timing;
};

/// Computes, for every row i with AOI box A_i = position_i +- aoi_half_i, grown box
/// G_i = position_i +- (aoi_half_i + h) and presence box P_j = position_j +- body_half_j (the float
/// expressions of build_step_boxes, host_visibility_engine.h):
///  - candidates(i) = { j != i : G_i meets P_j (closed boxes) and visibility_j & sees_i != 0 };
///  - a candidate whose handle was in the previous visible set of the same observer (the row with
///    the same handle in the previous update; none for a new observer) stays; any other enters
///    only if A_i meets P_j; previous entries that are no candidates leave;
///  - visible(i) = the stayed ones and the enters, by handle;
///  - with max_visible = m > 0 (caps_visible engines only): visible(i) keeps its m closest entries
///    (squared centre distance, ties by handle), and enters and leaves are the difference of that
///    set with the previous one.
/// Holds the previous update's visible sets itself (by the rows of that update).
class visibility_engine {
 public:
  visibility_engine() = default;
  visibility_engine(const visibility_engine&) = delete;
  visibility_engine& operator=(const visibility_engine&) = delete;
  virtual ~visibility_engine() = default;

  /// One update. On invalid input (a non-finite or inverted box) returns the index of the first
  /// invalid box in build_step_boxes' numbering (2i: row i's grown AOI box, 2i + 1: its presence box)
  /// and changes nothing: the previous sets stay. Throws std::runtime_error on a device error
  /// (then the engine's state is unspecified: load_previous before using it again). `out` is
  /// written only on success; the lists of the last successful update stay readable until then.
  [[nodiscard]] virtual std::optional<std::size_t> update(const visibility_input& in, visibility_output& out) = 0;

  /// Replaces the previous update's rows and visible sets (for a caller that made the last
  /// update without the engine): row r is observer ids[r]; `offsets` has rows + 1 entries, row
  /// r's handles are visible[offsets[r], offsets[r + 1]), sorted ascending. Empty spans: no
  /// previous update.
  virtual void load_previous(std::span<const std::uint32_t> ids, std::uint32_t slot_bits,
                             std::span<const std::uint32_t> offsets, std::span<const std::uint32_t> visible) = 0;

  /// A hint that an update follows soon (e.g. a millisecond before a tick): a device idle since
  /// the last one is woken now rather than inside the update. Never throws; may do nothing.
  virtual void prepare() noexcept {}

  /// Every row's visible set of the last successful update (after an update with `wanted`),
  /// valid until the next update or load_previous. Waits for the copy.
  [[nodiscard]] virtual visibility_lists fetch_all_visible() = 0;

  /// The last successful update's visible sets where the engine keeps them, for another engine
  /// of the same device to read in place (replication: interest/replication_engine.h): row r's
  /// handles are data[off[r], off[r + 1]), rows rows, total entries in all. All null / 0 when the
  /// engine keeps none (the default). Valid until the next update or load_previous.
  struct resident_lists {
    const std::uint32_t* data = nullptr;
    const std::uint32_t* off = nullptr;
    std::size_t rows = 0;
    std::uint64_t total = 0;
  };
  [[nodiscard]] virtual resident_lists resident_visible() const { return {}; }

  /// Whether update() honours visibility_input::max_visible (false: a caller with a cap uses
  /// another engine).
  [[nodiscard]] virtual bool caps_visible() const { return false; }

  [[nodiscard]] virtual const char* name() const = 0;
};

}  // namespace zone::interest
