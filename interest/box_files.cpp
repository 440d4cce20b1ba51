// Box files: the CSV text format and the binary ".boxes" format (docs/embedding.md, "Box files").
//
// The CSV reader streams: the file is read 1 MiB at a time and parsed line by line (string_view
// and std::from_chars), so what it holds beyond the boxes themselves is one chunk and at most one
// unfinished line of max_csv_line_bytes; a longer line (a file that is not CSV, /dev/zero) is an
// error naming it. The binary reader reads one fread per column straight into the box_set's
// vectors. Both validate every box. Both writers write PATH.tmp and rename it over PATH, so a failed write
// never leaves a partial file behind.
#include <algorithm>
#include <bit>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <system_error>
#include <vector>

#include "interest.h"

namespace zone::interest {
namespace {

// ---- Shared helpers -------------------------------------------------------------------------

constexpr char binary_magic[8] = {'Z', 'B', 'O', 'X', 'E', 'S', '0', '1'};
constexpr std::uint32_t binary_version = 1;
constexpr std::uint32_t flag_category_mask = 1u << 0;
constexpr std::uint32_t known_flags = flag_category_mask;
constexpr std::size_t header_bytes = 24;  // magic 8, version 4, flags 4, count 8
/// Box ids are 32-bit: a set may hold at most 2^32 boxes (ids 0 .. 2^32-1).
constexpr std::uint64_t max_boxes = std::uint64_t{1} << 32;
/// The longest CSV line (a box line is at most ~150 bytes; comments may be longer).
constexpr std::size_t max_csv_line_bytes = 4096;

std::string errno_text(int err) { return std::generic_category().message(err); }

file_error io_error(const std::string& what, const std::string& path, int err) {
  return file_error{0, what + " '" + path + "': " + errno_text(err)};
}

/// Closes a FILE* on every path out of a function.
struct file_closer {
  void operator()(std::FILE* f) const {
    if (f) std::fclose(f);
  }
};
using file_ptr = std::unique_ptr<std::FILE, file_closer>;

/// Size of an open regular file, or -1 when it cannot be told (a pipe, say).
long long file_size_of(std::FILE* f) {
  if (std::fseek(f, 0, SEEK_END) != 0) return -1;
  const long long size = std::ftell(f);
  if (std::fseek(f, 0, SEEK_SET) != 0) return -1;
  return size;
}

/// Writes to PATH.tmp, then renames it over PATH; on any failure the temporary is removed.
class atomic_writer {
 public:
  explicit atomic_writer(const std::string& path) : path_(path), tmp_(path + ".tmp") {}
  ~atomic_writer() {
    if (file_) {
      file_.reset();
      std::remove(tmp_.c_str());
    }
  }
  atomic_writer(const atomic_writer&) = delete;
  atomic_writer& operator=(const atomic_writer&) = delete;

  std::optional<file_error> open() {
    file_.reset(std::fopen(tmp_.c_str(), "wb"));
    if (!file_) return io_error("cannot create", tmp_, errno);
    return std::nullopt;
  }
  /// Returns false on a write error (the error is reported by commit()).
  bool write(const void* data, std::size_t bytes) {
    if (failed_ || bytes == 0) return !failed_;
    if (std::fwrite(data, 1, bytes, file_.get()) != bytes) {
      failed_ = true;
      errno_ = errno;
    }
    return !failed_;
  }
  std::optional<file_error> commit() {
    if (!failed_ && std::fflush(file_.get()) != 0) {
      failed_ = true;
      errno_ = errno;
    }
    if (failed_) return io_error("cannot write", tmp_, errno_);  // destructor removes the temporary
    const int rc = std::fclose(file_.release());
    if (rc != 0) {
      const int err = errno;
      std::remove(tmp_.c_str());
      return io_error("cannot write", tmp_, err);
    }
    if (std::rename(tmp_.c_str(), path_.c_str()) != 0) {
      const int err = errno;
      std::remove(tmp_.c_str());
      return io_error("cannot rename '" + tmp_ + "' to", path_, err);
    }
    return std::nullopt;
  }

 private:
  std::string path_, tmp_;
  file_ptr file_;
  bool failed_ = false;
  int errno_ = 0;
};

// ---- CSV ------------------------------------------------------------------------------------

constexpr bool is_blank(char c) { return c == ' ' || c == '\t'; }

std::string_view trim(std::string_view s) {
  while (!s.empty() && is_blank(s.front())) s.remove_prefix(1);
  while (!s.empty() && is_blank(s.back())) s.remove_suffix(1);
  return s;
}

/// A field as quoted in messages (long fields shortened).
std::string quoted(std::string_view field) {
  constexpr std::size_t max_shown = 40;
  std::string q = "'";
  if (field.size() > max_shown) {
    q.append(field.substr(0, max_shown));
    q += "...";
  } else {
    q.append(field);
  }
  q += '\'';
  return q;
}

std::string line_prefix(std::size_t line) { return "line " + std::to_string(line) + ": "; }

file_error field_error(std::size_t line, std::size_t field_index, std::string_view field, std::string_view what) {
  return file_error{line, line_prefix(line) + "field " + std::to_string(field_index + 1) + " (" + quoted(field) + ") " +
                              std::string(what)};
}

/// Allows one leading '+' (from_chars does not), but never "+-" or "++".
std::string_view strip_plus(std::string_view s) {
  if (s.size() >= 2 && s[0] == '+' && s[1] != '+' && s[1] != '-') s.remove_prefix(1);
  return s;
}

/// Parses one coordinate field (already trimmed). Returns an error text naming the field's role
/// `what` ("minx", ...), or an empty string on success.
std::string parse_coordinate(std::string_view field, float& value, const char* what) {
  const std::string_view s = strip_plus(field);
  const char* first = s.data();
  const char* last = s.data() + s.size();
  auto [ptr, ec] = std::from_chars(first, last, value);
  if (ec == std::errc::invalid_argument || ptr == first) return std::string("is not a number (") + what + ")";
  if (ptr != last) return std::string("has trailing garbage after the number (") + what + ")";
  if (ec == std::errc::result_out_of_range) {
    // Overflow is an error; underflow (e.g. 1e-50) rounds to zero or a subnormal, as strtof does.
    const std::string copy(s);
    const float v = std::strtof(copy.c_str(), nullptr);
    if (std::isinf(v)) return std::string("is out of the range of a 32-bit float (") + what + ")";
    value = v;
    return {};
  }
  if (std::isnan(value)) return std::string("is NaN (") + what + "; coordinates must be finite)";
  if (std::isinf(value)) return std::string("is infinite (") + what + "; coordinates must be finite)";
  return {};
}

/// Parses a category or mask field (already trimmed). Returns an error text naming `what`
/// ("category" or "mask"), or an empty string on success.
std::string parse_bits(std::string_view field, std::uint32_t& value, const char* what) {
  const std::string_view s = strip_plus(field);
  const char* first = s.data();
  const char* last = s.data() + s.size();
  if (!s.empty() && s.front() == '-') return std::string("is negative (") + what + " must be an unsigned 32-bit integer)";
  auto [ptr, ec] = std::from_chars(first, last, value);
  if (ec == std::errc::invalid_argument || ptr == first) return std::string("is not an unsigned 32-bit integer (") + what + ")";
  if (ec == std::errc::result_out_of_range) return std::string("is out of range (") + what + " must be at most 4294967295)";
  if (ptr != last) return std::string("has trailing garbage after the integer (") + what + ")";
  return {};
}

constexpr const char* field_names[6] = {"minx", "miny", "minz", "maxx", "maxy", "maxz"};

/// The fast path for an ordinary box line: plain numbers, optional blanks around fields, 6 or 8
/// fields, finite coordinates with lo <= hi. Returns false for anything else; the caller then runs
/// parse_box_line, which accepts a superset (a leading '+', float underflow) and describes errors.
/// Everything this accepts, parse_box_line accepts with the same values.
bool parse_box_line_fast(const char* p, const char* end, box& b) {
  const auto skip_blanks = [&] {
    while (p != end && is_blank(*p)) ++p;
  };
  float v[6];
  for (int k = 0; k < 6; ++k) {
    skip_blanks();
    const auto [ptr, ec] = std::from_chars(p, end, v[k]);
    if (ec != std::errc{} || ptr == p) return false;
    p = ptr;
    skip_blanks();
    if (k < 5) {
      if (p == end || *p != ',') return false;
      ++p;
    }
  }
  std::uint32_t bits[2] = {1, 1};
  if (p != end) {
    for (int k = 0; k < 2; ++k) {
      if (p == end || *p != ',') return false;
      ++p;
      skip_blanks();
      const auto [ptr, ec] = std::from_chars(p, end, bits[k]);
      if (ec != std::errc{} || ptr == p) return false;
      p = ptr;
      skip_blanks();
    }
    if (p != end) return false;
  }
  // NaN fails every comparison; infinities fail the range test.
  constexpr float big = std::numeric_limits<float>::max();
  bool ok = true;
  for (int d = 0; d < 3; ++d) ok &= v[d] <= v[d + 3] && v[d] >= -big && v[d + 3] <= big;
  if (!ok) return false;
  for (int d = 0; d < 3; ++d) {
    b.lo[d] = v[d];
    b.hi[d] = v[d + 3];
  }
  b.category = bits[0];
  b.mask = bits[1];
  return true;
}

/// Parses one box line (already stripped of '\r' and known not blank or a comment).
std::optional<file_error> parse_box_line(std::string_view text, std::size_t line, std::size_t box_index, box& b);

/// CSV text fed in pieces: complete lines are parsed as they come, an unfinished one is kept
/// (at most max_csv_line_bytes). Errors name the line; after one, `out` is cleared.
class csv_stream {
 public:
  explicit csv_stream(box_set& out) : out_(out) { out_.clear(); }
  std::optional<file_error> feed(std::string_view chunk) {
    while (!chunk.empty()) {
      const std::size_t nl = chunk.find('\n');
      if (nl == std::string_view::npos) {
        if (partial_.size() + chunk.size() > max_csv_line_bytes) return fail(too_long());
        partial_.append(chunk);
        return std::nullopt;
      }
      std::optional<file_error> err;
      if (partial_.empty()) {
        err = row(chunk.substr(0, nl));
      } else {
        if (partial_.size() + nl > max_csv_line_bytes) return fail(too_long());
        partial_.append(chunk.substr(0, nl));
        err = row(partial_);
        partial_.clear();
      }
      if (err) return fail(std::move(*err));
      chunk.remove_prefix(nl + 1);
    }
    return std::nullopt;
  }
  /// The last line (without a line break) and the end.
  std::optional<file_error> finish() {
    if (partial_.empty()) return std::nullopt;
    auto err = row(partial_);
    partial_.clear();
    if (err) return fail(std::move(*err));
    return std::nullopt;
  }

 private:
  file_error too_long() const {
    return file_error{line_ + 1, line_prefix(line_ + 1) + "longer than " + std::to_string(max_csv_line_bytes) +
                                     " bytes without a line break (not a CSV box file?)"};
  }
  file_error fail(file_error e) {
    out_.clear();
    return e;
  }
  std::optional<file_error> row(std::string_view r) {
    ++line_;
    if (r.size() > max_csv_line_bytes) return too_long_at(line_);
    if (line_ == 1 && r.starts_with("\xEF\xBB\xBF")) r.remove_prefix(3);  // UTF-8 byte-order mark
    if (!r.empty() && r.back() == '\r') r.remove_suffix(1);
    const std::size_t first = r.find_first_not_of(" \t");
    if (first == std::string_view::npos || r[first] == '#') return std::nullopt;
    if (out_.size() == max_boxes) {
      return file_error{line_, line_prefix(line_) + "too many boxes (at most 2^32; box ids are 32-bit)"};
    }
    if (!parse_box_line_fast(r.data(), r.data() + r.size(), b_)) {
      if (auto err = parse_box_line(r, line_, out_.size(), b_)) return err;
    }
    out_.push_back(b_);
    return std::nullopt;
  }
  static file_error too_long_at(std::size_t line) {
    return file_error{line, line_prefix(line) + "longer than " + std::to_string(max_csv_line_bytes) +
                                " bytes (not a CSV box file?)"};
  }

  box_set& out_;
  std::string partial_;
  std::size_t line_ = 0;
  box b_;
};

std::optional<file_error> parse_box_line(std::string_view text, std::size_t line, std::size_t box_index, box& b) {
  std::string_view fields[8];
  std::size_t count = 0;
  std::size_t start = 0;
  for (;;) {
    const std::size_t comma = text.find(',', start);
    const std::string_view field = text.substr(start, comma == std::string_view::npos ? std::string_view::npos : comma - start);
    if (count < 8) fields[count] = trim(field);
    ++count;
    if (comma == std::string_view::npos) break;
    start = comma + 1;
  }
  if (count != 6 && count != 8) {
    return file_error{line, line_prefix(line) + "expected 6 or 8 comma-separated fields "
                                                "(minx,miny,minz,maxx,maxy,maxz[,category,mask]), found " +
                                std::to_string(count)};
  }
  for (std::size_t k = 0; k < 6; ++k) {
    float& v = k < 3 ? b.lo[k] : b.hi[k - 3];
    if (auto why = parse_coordinate(fields[k], v, field_names[k]); !why.empty()) return field_error(line, k, fields[k], why);
  }
  b.category = 1;
  b.mask = 1;
  if (count == 8) {
    if (auto why = parse_bits(fields[6], b.category, "category"); !why.empty()) return field_error(line, 6, fields[6], why);
    if (auto why = parse_bits(fields[7], b.mask, "mask"); !why.empty()) return field_error(line, 7, fields[7], why);
  }
  for (std::size_t d = 0; d < 3; ++d) {
    if (b.lo[d] > b.hi[d]) {
      static constexpr char axis[3] = {'x', 'y', 'z'};
      return file_error{line, line_prefix(line) + "box " + std::to_string(box_index) + ": lo." + axis[d] + " = " +
                                  std::string(fields[d]) + " > hi." + axis[d] + " = " + std::string(fields[d + 3]) +
                                  " (min" + axis[d] + " must not exceed max" + axis[d] + ")"};
    }
  }
  // The library's own check, as a safety net (NaN/Inf and lo > hi were reported above with more detail).
  if (auto err = validate_box(b, box_index)) return file_error{line, line_prefix(line) + err->message};
  return std::nullopt;
}

// ---- Binary ---------------------------------------------------------------------------------

void put_u32(unsigned char* p, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) p[i] = static_cast<unsigned char>(v >> (8 * i));
}
void put_u64(unsigned char* p, std::uint64_t v) {
  for (int i = 0; i < 8; ++i) p[i] = static_cast<unsigned char>(v >> (8 * i));
}
std::uint32_t get_u32(const unsigned char* p) {
  std::uint32_t v = 0;
  for (int i = 3; i >= 0; --i) v = (v << 8) | p[i];
  return v;
}
std::uint64_t get_u64(const unsigned char* p) {
  std::uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | p[i];
  return v;
}

/// Columns are stored little-endian; on a big-endian host swap each 32-bit word in place.
template <class T>
void to_or_from_little_endian(std::vector<T>& column) {
  static_assert(sizeof(T) == 4);
  if constexpr (std::endian::native == std::endian::big) {
    for (auto& x : column) {
      auto u = std::bit_cast<std::uint32_t>(x);
      u = (u >> 24) | ((u >> 8) & 0xff00u) | ((u << 8) & 0xff0000u) | (u << 24);
      x = std::bit_cast<T>(u);
    }
  }
}

template <class T>
bool write_column(atomic_writer& w, const std::vector<T>& column) {
  if constexpr (std::endian::native == std::endian::big) {
    std::vector<T> copy(column);
    to_or_from_little_endian(copy);
    return w.write(copy.data(), copy.size() * sizeof(T));
  } else {
    return w.write(column.data(), column.size() * sizeof(T));
  }
}

/// Reads a binary box file from `f`, positioned at its start. `size` is the file's size (-1: unknown).
std::optional<file_error> read_binary(std::FILE* f, const std::string& path, long long size, box_set& out) {
  out.clear();
  unsigned char header[header_bytes];
  const std::size_t got = std::fread(header, 1, header_bytes, f);
  if (std::ferror(f)) return io_error("cannot read", path, errno);
  if (got < sizeof binary_magic || std::memcmp(header, binary_magic, sizeof binary_magic) != 0) {
    return file_error{0, "bad magic (not a ZBOXES01 binary box file)"};
  }
  if (got < header_bytes) {
    return file_error{0, "truncated header (" + std::to_string(got) + " of " + std::to_string(header_bytes) + " bytes)"};
  }
  const std::uint32_t version = get_u32(header + 8);
  const std::uint32_t flags = get_u32(header + 12);
  const std::uint64_t count = get_u64(header + 16);
  if (version != binary_version) {
    return file_error{0, "unsupported version " + std::to_string(version) + " (this reader knows version " +
                             std::to_string(binary_version) + ")"};
  }
  if ((flags & ~known_flags) != 0) {
    return file_error{0, "unsupported flags " + std::to_string(flags) + " (known: bit 0, category/mask columns)"};
  }
  const bool has_bits = (flags & flag_category_mask) != 0;
  const std::uint64_t bytes_per_box = 6 * sizeof(float) + (has_bits ? 2 * sizeof(std::uint32_t) : 0);
  if (count > max_boxes) {
    return file_error{0, "header claims " + std::to_string(count) + " boxes; at most 2^32 are supported"};
  }
  const std::uint64_t expected = header_bytes + count * bytes_per_box;  // no overflow: count <= 2^32
  if (size >= 0 && static_cast<std::uint64_t>(size) != expected) {
    const std::string sizes = "header says " + std::to_string(count) + " boxes (" + std::to_string(expected) +
                              " bytes), file has " + std::to_string(size) + " bytes";
    if (static_cast<std::uint64_t>(size) < expected) return file_error{0, "truncated: " + sizes};
    return file_error{0, "wrong size, trailing data: " + sizes};
  }

  out.resize(static_cast<std::size_t>(count));
  const auto read_column = [&](auto& column) -> std::optional<file_error> {
    const std::size_t n = std::fread(column.data(), sizeof(column[0]), column.size(), f);
    if (n != column.size()) {
      if (std::ferror(f)) return io_error("cannot read", path, errno);
      return file_error{0, "truncated: the columns end early"};
    }
    to_or_from_little_endian(column);
    return std::nullopt;
  };
  for (auto* column : {&out.lo_x, &out.lo_y, &out.lo_z, &out.hi_x, &out.hi_y, &out.hi_z}) {
    if (auto err = read_column(*column)) {
      out.clear();
      return err;
    }
  }
  if (has_bits) {
    for (auto* column : {&out.category, &out.mask}) {
      if (auto err = read_column(*column)) {
        out.clear();
        return err;
      }
    }
  }
  if (size < 0 && std::fgetc(f) != EOF) {  // size unknown beforehand (not a regular file)
    out.clear();
    return file_error{0, "wrong size, trailing data after " + std::to_string(count) + " boxes"};
  }
  if (auto err = validate(out)) {
    out.clear();
    return file_error{0, err->message};
  }
  return std::nullopt;
}

}  // namespace

// ---- Public API -----------------------------------------------------------------------------

std::optional<file_error> parse_csv(std::string_view text, box_set& out) {
  csv_stream csv(out);
  out.reserve(static_cast<std::size_t>(std::count(text.begin(), text.end(), '\n')) + 1);
  if (auto err = csv.feed(text)) return err;
  return csv.finish();
}

namespace {
/// Streams the rest of `f` through a CSV parser; `head` is what was read of it already.
std::optional<file_error> read_csv_stream(std::FILE* f, const std::string& path, std::string_view head, box_set& out) {
  csv_stream csv(out);
  if (auto err = csv.feed(head)) return err;
  std::vector<char> chunk(std::size_t{1} << 20);
  for (;;) {
    const std::size_t got = std::fread(chunk.data(), 1, chunk.size(), f);
    if (got == 0) break;
    if (auto err = csv.feed({chunk.data(), got})) return err;
  }
  if (std::ferror(f)) {
    out.clear();
    return io_error("cannot read", path, errno);
  }
  return csv.finish();
}
}  // namespace

std::optional<file_error> read_csv_file(const std::string& path, box_set& out) {
  out.clear();
  file_ptr f(std::fopen(path.c_str(), "rb"));
  if (!f) return io_error("cannot open", path, errno);
  return read_csv_stream(f.get(), path, {}, out);
}

std::optional<file_error> write_csv_file(const std::string& path, const box_set& boxes) {
  atomic_writer w(path);
  if (auto err = w.open()) return err;
  std::vector<char> buffer(std::size_t{1} << 20);
  std::size_t used = 0;
  constexpr std::size_t max_row = 8 * 24 + 16;  // 8 fields of at most ~16 characters each, commas, newline
  static constexpr char header[] = "# minx,miny,minz,maxx,maxy,maxz,category,mask\n";
  std::memcpy(buffer.data(), header, sizeof header - 1);
  used = sizeof header - 1;
  for (std::size_t i = 0; i < boxes.size(); ++i) {
    if (buffer.size() - used < max_row) {
      if (!w.write(buffer.data(), used)) break;
      used = 0;
    }
    char* p = buffer.data() + used;
    char* const limit = buffer.data() + buffer.size();
    for (const auto* column : {&boxes.lo_x, &boxes.lo_y, &boxes.lo_z, &boxes.hi_x, &boxes.hi_y, &boxes.hi_z}) {
      p = std::to_chars(p, limit, (*column)[i]).ptr;  // shortest representation that round-trips
      *p++ = ',';
    }
    p = std::to_chars(p, limit, boxes.category[i]).ptr;
    *p++ = ',';
    p = std::to_chars(p, limit, boxes.mask[i]).ptr;
    *p++ = '\n';
    used = static_cast<std::size_t>(p - buffer.data());
  }
  w.write(buffer.data(), used);
  return w.commit();
}

std::optional<file_error> read_binary_file(const std::string& path, box_set& out) {
  out.clear();
  file_ptr f(std::fopen(path.c_str(), "rb"));
  if (!f) return io_error("cannot open", path, errno);
  const long long size = file_size_of(f.get());
  return read_binary(f.get(), path, size, out);
}

std::optional<file_error> write_binary_file(const std::string& path, const box_set& boxes) {
  atomic_writer w(path);
  if (auto err = w.open()) return err;
  const bool has_bits = std::any_of(boxes.category.begin(), boxes.category.end(), [](std::uint32_t c) { return c != 1; }) ||
                        std::any_of(boxes.mask.begin(), boxes.mask.end(), [](std::uint32_t m) { return m != 1; });
  unsigned char header[header_bytes];
  std::memcpy(header, binary_magic, sizeof binary_magic);
  put_u32(header + 8, binary_version);
  put_u32(header + 12, has_bits ? flag_category_mask : 0u);
  put_u64(header + 16, boxes.size());
  w.write(header, sizeof header);
  for (const auto* column : {&boxes.lo_x, &boxes.lo_y, &boxes.lo_z, &boxes.hi_x, &boxes.hi_y, &boxes.hi_z}) {
    write_column(w, *column);
  }
  if (has_bits) {
    write_column(w, boxes.category);
    write_column(w, boxes.mask);
  }
  return w.commit();
}

std::optional<file_error> read_box_file(const std::string& path, box_set& out) {
  out.clear();
  file_ptr f(std::fopen(path.c_str(), "rb"));
  if (!f) return io_error("cannot open", path, errno);
  const long long size = file_size_of(f.get());  // -1 for a pipe: then nothing can be re-read
  std::string text(sizeof binary_magic, '\0');
  text.resize(std::fread(text.data(), 1, text.size(), f.get()));
  if (std::ferror(f.get())) return io_error("cannot read", path, errno);
  if (text.size() == sizeof binary_magic && std::memcmp(text.data(), binary_magic, sizeof binary_magic) == 0) {
    if (size < 0 || std::fseek(f.get(), 0, SEEK_SET) != 0) {
      return file_error{0, "a binary box file must be a regular (seekable) file"};
    }
    return read_binary(f.get(), path, size, out);
  }
  return read_csv_stream(f.get(), path, text, out);
}

}  // namespace zone::interest
