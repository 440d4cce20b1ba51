// Box files: the CSV parser's every error path, the CSV and binary round trips, the binary
// format's byte layout and its rejection of damaged files (docs/embedding.md).
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <bit>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "interest/interest.h"

using namespace zone::interest;
namespace fs = std::filesystem;

namespace {

using zone::test::fresh_seed;

/// A scratch folder, removed at the end of the test.
struct temp_dir {
  fs::path path;
  temp_dir() {
    path = fs::temp_directory_path() / ("zone_box_files_" + std::to_string(fresh_seed()));
    fs::create_directories(path);
  }
  ~temp_dir() {
    std::error_code ec;
    fs::remove_all(path, ec);
  }
  [[nodiscard]] std::string file(const std::string& name) const { return (path / name).string(); }
};

std::string read_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

void write_bytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

/// Bit-for-bit equality of two float columns (distinguishes -0 from +0).
bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  if (a.size() != b.size()) return false;
  for (std::size_t i = 0; i < a.size(); ++i) {
    if (std::bit_cast<std::uint32_t>(a[i]) != std::bit_cast<std::uint32_t>(b[i])) return false;
  }
  return true;
}

bool same_sets(const box_set& a, const box_set& b) {
  return same_bits(a.lo_x, b.lo_x) && same_bits(a.lo_y, b.lo_y) && same_bits(a.lo_z, b.lo_z) &&
         same_bits(a.hi_x, b.hi_x) && same_bits(a.hi_y, b.hi_y) && same_bits(a.hi_z, b.hi_z) &&
         a.category == b.category && a.mask == b.mask;
}

/// Random finite float of any magnitude (all exponents, subnormals, both zeros) or a special value.
float random_finite(std::mt19937_64& rng) {
  static constexpr float specials[] = {0.0f,
                                       -0.0f,
                                       std::numeric_limits<float>::denorm_min(),
                                       -std::numeric_limits<float>::denorm_min(),
                                       std::numeric_limits<float>::min(),
                                       std::numeric_limits<float>::max(),
                                       std::numeric_limits<float>::lowest(),
                                       0.1f,
                                       1.0f / 3.0f,
                                       16777217.0f};
  const auto pick = rng() % 8;
  if (pick == 0) return specials[rng() % std::size(specials)];
  if (pick < 4) return std::uniform_real_distribution<float>(-1e4f, 1e4f)(rng);
  for (;;) {
    const float f = std::bit_cast<float>(static_cast<std::uint32_t>(rng()));
    if (std::isfinite(f)) return f;
  }
}

box_set random_set(std::uint64_t seed, std::size_t n, bool with_bits) {
  std::mt19937_64 rng(seed);
  box_set s;
  for (std::size_t i = 0; i < n; ++i) {
    box b;
    for (int d = 0; d < 3; ++d) {
      float x = random_finite(rng), y = random_finite(rng);
      if (y < x) std::swap(x, y);
      b.lo[d] = x;
      b.hi[d] = y;
    }
    if (with_bits) {
      b.category = static_cast<std::uint32_t>(rng());
      b.mask = rng() % 4 == 0 ? 0xffffffffu : static_cast<std::uint32_t>(rng());
    }
    s.push_back(b);
  }
  return s;
}

/// Parses text that must fail; checks the reported line and that the message names it and holds `phrase`.
void expect_csv_error(const std::string& text, std::size_t line, const std::string& phrase) {
  CAPTURE(text);
  box_set out;
  out.push_back(box{});
  const auto err = parse_csv(text, out);
  REQUIRE(err.has_value());
  CAPTURE(err->message);
  CHECK(err->line == line);
  CHECK(err->message.starts_with("line " + std::to_string(line) + ": "));
  CHECK(err->message.find(phrase) != std::string::npos);
  CHECK(out.empty());  // nothing half-parsed is handed back
}

// Binary layout constants, as documented in docs/embedding.md.
constexpr std::size_t header_size = 24;

std::uint32_t le32(const std::string& bytes, std::size_t offset) {
  std::uint32_t v = 0;
  for (int i = 3; i >= 0; --i) v = (v << 8) | static_cast<unsigned char>(bytes[offset + static_cast<std::size_t>(i)]);
  return v;
}
std::uint64_t le64(const std::string& bytes, std::size_t offset) {
  std::uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | static_cast<unsigned char>(bytes[offset + static_cast<std::size_t>(i)]);
  return v;
}
void put_le32(std::string& bytes, std::size_t offset, std::uint32_t v) {
  for (std::size_t i = 0; i < 4; ++i) bytes[offset + i] = static_cast<char>(v >> (8 * i));
}

/// Writes `original` to `path` with `write` (no temporary file is left), reads it back with
/// `read` and with read_box_file: the same set both times. `written` checks the file in between.
template <class Written = void (*)()>
void check_round_trip(const std::string& path, const box_set& original, std::optional<file_error> (*write)(const std::string&, const box_set&),
                      std::optional<file_error> (*read)(const std::string&, box_set&), Written written = [] {}) {
  REQUIRE_FALSE(write(path, original).has_value());
  CHECK_FALSE(fs::exists(path + ".tmp"));
  written();
  box_set back;
  const auto err = read(path, back);
  CAPTURE(err ? err->message : std::string());
  REQUIRE_FALSE(err.has_value());
  CHECK(same_sets(original, back));
  box_set any;
  REQUIRE_FALSE(read_box_file(path, any).has_value());
  CHECK(same_sets(original, any));
}

}  // namespace

TEST_SUITE("interest.files") {
  // ---- CSV: accepted input ----------------------------------------------------------------

  TEST_CASE("csv: comments, blank lines, CRLF, spaces and mixed 6/8-field lines") {
    const std::string text =
        "# a comment\r\n"
        "\r\n"
        "0,0,0,1,1,1\r\n"
        "   \t  \n"
        "  # an indented comment\n"
        " 1.5 ,\t-2 , 3e2,  4,5 ,6e2 , 7 , 8 \r\n"
        "\n"
        "-1,-2,-3,-0.5,-1.5,-2.5,0,4294967295";  // no final newline
    box_set s;
    const auto err = parse_csv(text, s);
    REQUIRE_FALSE(err.has_value());
    REQUIRE(s.size() == 3);
    const box b0 = s.get(0), b1 = s.get(1), b2 = s.get(2);
    CHECK(b0.lo[0] == 0.0f);
    CHECK(b0.hi[2] == 1.0f);
    CHECK(b0.category == 1);  // 6 fields: defaults
    CHECK(b0.mask == 1);
    CHECK(b1.lo[0] == 1.5f);
    CHECK(b1.lo[1] == -2.0f);
    CHECK(b1.lo[2] == 300.0f);
    CHECK(b1.hi[0] == 4.0f);
    CHECK(b1.hi[1] == 5.0f);
    CHECK(b1.hi[2] == 600.0f);
    CHECK(b1.category == 7);
    CHECK(b1.mask == 8);
    CHECK(b2.lo[2] == -3.0f);
    CHECK(b2.hi[2] == -2.5f);
    CHECK(b2.category == 0);
    CHECK(b2.mask == 4294967295u);
  }

  TEST_CASE("csv: empty text, only comments, BOM, leading '+', float underflow") {
    box_set s;
    s.push_back(box{});
    REQUIRE_FALSE(parse_csv("", s).has_value());
    CHECK(s.empty());
    REQUIRE_FALSE(parse_csv("# nothing\n\n   \n", s).has_value());
    CHECK(s.empty());
    REQUIRE_FALSE(parse_csv("\xEF\xBB\xBF" "0,0,0,1,1,1\n", s).has_value());
    CHECK(s.size() == 1);
    REQUIRE_FALSE(parse_csv("+1,+2,0,+3,4,1e-50,+5,+6\n", s).has_value());
    REQUIRE(s.size() == 1);
    CHECK(s.lo_x[0] == 1.0f);
    CHECK(s.hi_x[0] == 3.0f);
    CHECK(s.hi_z[0] == 0.0f);  // underflow rounds to zero, like strtof
    CHECK(s.category[0] == 5);
    CHECK(s.mask[0] == 6);
    // Touching and degenerate boxes are valid (closed boxes; lo == hi allowed).
    REQUIRE_FALSE(parse_csv("2,2,2,2,2,2\n", s).has_value());
    CHECK(s.size() == 1);
  }

  TEST_CASE("csv: a box's id is its index among box lines, not its line number") {
    box_set s;
    REQUIRE_FALSE(parse_csv("# header\n\n5,5,5,6,6,6\n# mid\n7,7,7,8,8,8\n", s).has_value());
    REQUIRE(s.size() == 2);
    CHECK(s.lo_x[0] == 5.0f);
    CHECK(s.lo_x[1] == 7.0f);
  }

  TEST_CASE("csv: category and mask limits") {
    box_set s;
    REQUIRE_FALSE(parse_csv("0,0,0,1,1,1,4294967295,4294967295\n", s).has_value());
    CHECK(s.category[0] == 4294967295u);
    CHECK(s.mask[0] == 4294967295u);
    REQUIRE_FALSE(parse_csv("0,0,0,1,1,1,0,0\n", s).has_value());
    CHECK(s.category[0] == 0u);
    expect_csv_error("0,0,0,1,1,1,4294967296,1\n", 1, "field 7 ('4294967296') is out of range");
    expect_csv_error("0,0,0,1,1,1\n0,0,0,1,1,1,1,4294967296\n", 2, "field 8 ('4294967296') is out of range");
    expect_csv_error("0,0,0,1,1,1,-1,1\n", 1, "field 7 ('-1') is negative");
    expect_csv_error("0,0,0,1,1,1,1,-1\n", 1, "field 8 ('-1') is negative");
    expect_csv_error("0,0,0,1,1,1,abc,1\n", 1, "field 7 ('abc') is not an unsigned 32-bit integer (category)");
    expect_csv_error("0,0,0,1,1,1,1,x\n", 1, "field 8 ('x') is not an unsigned 32-bit integer (mask)");
    expect_csv_error("0,0,0,1,1,1,1.5,1\n", 1, "field 7 ('1.5') has trailing garbage");
    expect_csv_error("0,0,0,1,1,1,,1\n", 1, "field 7 ('') is not an unsigned 32-bit integer");
  }

  // ---- CSV: every error path --------------------------------------------------------------

  TEST_CASE("csv: wrong field count") {
    expect_csv_error("0,0,0,1,1\n", 1, "expected 6 or 8 comma-separated fields");
    expect_csv_error("0,0,0,1,1\n", 1, "found 5");
    expect_csv_error("0,0,0,1,1,1\n0,0,0,1,1,1,1\n", 2, "found 7");
    expect_csv_error("0,0,0,1,1,1,1,1,1\n", 1, "found 9");
    expect_csv_error("0,0,0,1,1,1,\n", 1, "found 7");  // trailing comma
    expect_csv_error("0 0 0 1 1 1\n", 1, "found 1");
  }

  TEST_CASE("csv: unparsable numbers and trailing garbage") {
    expect_csv_error("0,0,abc,1,1,1\n", 1, "field 3 ('abc') is not a number");
    expect_csv_error("0,,0,1,1,1\n", 1, "field 2 ('') is not a number");
    expect_csv_error("0,0,0,1,1,1x\n", 1, "field 6 ('1x') has trailing garbage");
    expect_csv_error("0,0,0,1,1 2,1\n", 1, "field 5 ('1 2') has trailing garbage");
    expect_csv_error("0,0,0,1,1 2,1,1\n", 1, "found 7");
    expect_csv_error("0,0,0,1,1,1,1,1 x\n", 1, "field 8 ('1 x') has trailing garbage");
    expect_csv_error("0x10,0,0,1,1,1\n", 1, "field 1 ('0x10') has trailing garbage");
    expect_csv_error("+-1,0,0,1,1,1\n", 1, "field 1 ('+-1') is not a number");
    expect_csv_error("0,0,0,1,1e39,1\n", 1, "field 5 ('1e39') is out of the range of a 32-bit float");
  }

  TEST_CASE("csv: NaN and infinities are rejected, naming the field") {
    expect_csv_error("nan,0,0,1,1,1\n", 1, "field 1 ('nan') is NaN");
    expect_csv_error("0,0,0,1,NaN,1\n", 1, "field 5 ('NaN') is NaN");
    expect_csv_error("0,0,-nan,1,1,1\n", 1, "is NaN");
    expect_csv_error("0,0,0,1,1,nan(123)\n", 1, "is NaN");
    expect_csv_error("0,0,0,inf,1,1\n", 1, "field 4 ('inf') is infinite");
    expect_csv_error("-inf,0,0,1,1,1\n", 1, "field 1 ('-inf') is infinite");
    expect_csv_error("0,0,0,1,Infinity,1\n", 1, "is infinite");
  }

  TEST_CASE("csv: lo > hi names the axis and both values") {
    expect_csv_error("5,0,0,4,1,1\n", 1, "lo.x = 5 > hi.x = 4");
    expect_csv_error("0,0,0,1,1,1\n0,5.25,0,1,-3,1\n", 2, "lo.y = 5.25 > hi.y = -3");
    expect_csv_error("0,0,1.0000001,1,1,1\n", 1, "lo.z = 1.0000001 > hi.z = 1");
    expect_csv_error("0,0,0,1,1,1\n0,0,0,1,1,1\n0,0,9,1,1,8\n", 3, "box 2");
  }

  TEST_CASE("csv: line numbers count every line of the file (comments, blanks, CRLF)") {
    expect_csv_error("# c\r\n\r\n0,0,0,1,1,1\r\n   \r\n0,0,0,1,1\r\n", 5, "found 5");
    expect_csv_error("\n\n\n\n\n\n\n\n\n\n\n0,0,abc,1,1,1\n", 12, "line 12: field 3 ('abc') is not a number");
    expect_csv_error("0,0,0,1,1,1\r\n0,0,0,1,1,1\r\nnan,0,0,1,1,1\r\n", 3, "field 1 ('nan')");
    // The first error wins, even when later lines are bad too.
    expect_csv_error("0,0,0,1,1,1\n1,1\n2,2\n", 2, "found 2");
  }

  TEST_CASE("csv streaming: a file read in chunks parses as the whole text does; an overlong line is an error naming it") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    // ~3 MiB of lines of random lengths (comments of up to 4,000 bytes, CRLF, blanks), so lines
    // cross the reader's 1 MiB chunks at every kind of place.
    std::string text;
    std::size_t boxes = 0;
    while (text.size() < (std::size_t{3} << 20)) {
      switch (rng() % 5) {
        case 0: text += "# " + std::string(rng() % 4000, 'c') + "\n"; break;
        case 1: text += "\r\n"; break;
        default: {
          const float x = static_cast<float>(rng() % 1000) / 7;
          text += std::to_string(x) + "," + std::to_string(x) + ",0," + std::to_string(x + 1) + "," + std::to_string(x + 2) +
                  ",1" + (rng() % 2 ? ",3,5\r\n" : "\n");
          ++boxes;
        }
      }
    }
    text += "1,2,3,4,5,6";  // the last line without a line break
    ++boxes;
    const std::string path = (fs::temp_directory_path() / ("zone_stream_" + std::to_string(seed) + ".csv")).string();
    {
      std::ofstream f(path, std::ios::binary);
      f << text;
    }
    box_set whole, streamed;
    REQUIRE_FALSE(parse_csv(text, whole).has_value());
    REQUIRE_FALSE(read_box_file(path, streamed).has_value());
    CHECK(whole.size() == boxes);
    CHECK(streamed.size() == boxes);
    CHECK(streamed.lo_x == whole.lo_x);
    CHECK(streamed.hi_y == whole.hi_y);
    CHECK(streamed.mask == whole.mask);
    // A line over 4,096 bytes, in a file and in text: the error names it, nothing is kept.
    const std::string long_line = "1,2,3,4,5,6\n# fine\n" + std::string(5000, 'x') + "\n1,2,3,4,5,6\n";
    box_set bad;
    auto err = parse_csv(long_line, bad);
    REQUIRE(err.has_value());
    CHECK(err->line == 3);
    CHECK(err->message.find("line 3: longer than 4096 bytes") != std::string::npos);
    CHECK(bad.empty());
    {
      std::ofstream f(path, std::ios::binary);
      f << "1,2,3,4,5,6\n" << std::string(std::size_t{3} << 20, '\0');  // no line break for 3 MiB
    }
    err = read_box_file(path, bad);
    REQUIRE(err.has_value());
    CHECK(err->line == 2);
    CHECK(bad.empty());
    fs::remove(path);
  }

  TEST_CASE("csv: long fields are shortened in messages") {
    const std::string junk(200, 'z');
    box_set s;
    const auto err = parse_csv("0,0,0,1,1," + junk + "\n", s);
    REQUIRE(err.has_value());
    CHECK(err->message.size() < 200);
    CHECK(err->message.find("...") != std::string::npos);
  }

  // ---- CSV files --------------------------------------------------------------------------

  TEST_CASE("csv: write -> read round trip is bit-for-bit on random sets") {
    temp_dir dir;
    for (int round = 0; round < 4; ++round) {
      const std::uint64_t seed = fresh_seed();
      CAPTURE(seed);
      const box_set original = random_set(seed, 2000 + round * 137, round % 2 == 0);
      check_round_trip(dir.file("round.csv"), original, write_csv_file, read_csv_file);
    }
  }

  TEST_CASE("csv: the writer always writes category and mask") {
    temp_dir dir;
    box_set s;
    s.push_back(box{{0, 0, 0}, {1, 1, 1}, 1, 1});
    const std::string path = dir.file("bits.csv");
    REQUIRE_FALSE(write_csv_file(path, s).has_value());
    const std::string text = read_bytes(path);
    CHECK(text.find("0,0,0,1,1,1,1,1\n") != std::string::npos);
  }

  TEST_CASE("csv files: a missing input and an unwritable output are reported, nothing is left behind") {
    temp_dir dir;
    box_set s;
    const std::string missing = dir.file("missing.csv");
    const auto rerr = read_csv_file(missing, s);
    REQUIRE(rerr.has_value());
    CHECK(rerr->line == 0);
    CHECK(rerr->message.find("missing.csv") != std::string::npos);
    REQUIRE(read_box_file(missing, s).has_value());

    s.push_back(box{});
    const std::string nowhere = dir.file("no/such/folder/out.csv");
    REQUIRE(write_csv_file(nowhere, s).has_value());
    REQUIRE(write_binary_file(nowhere, s).has_value());
    CHECK_FALSE(fs::exists(nowhere));
    CHECK_FALSE(fs::exists(nowhere + ".tmp"));
  }

  TEST_CASE("csv files: a parse error in a file reports the file's line") {
    temp_dir dir;
    const std::string path = dir.file("bad.csv");
    write_bytes(path, "# boxes\r\n0,0,0,1,1,1\r\n0,0,0,1,1,1,-1,1\r\n");
    box_set s;
    auto err = read_csv_file(path, s);
    REQUIRE(err.has_value());
    CHECK(err->line == 3);
    CHECK(err->message.find("negative") != std::string::npos);
    err = read_box_file(path, s);
    REQUIRE(err.has_value());
    CHECK(err->line == 3);
  }

  // ---- Binary -----------------------------------------------------------------------------

  TEST_CASE("binary: write -> read round trip is bit-for-bit, with and without category/mask") {
    temp_dir dir;
    for (const bool with_bits : {true, false}) {
      const std::uint64_t seed = fresh_seed();
      CAPTURE(seed);
      CAPTURE(with_bits);
      const box_set original = random_set(seed, 5000, with_bits);
      const std::string path = dir.file("round.boxes");
      check_round_trip(path, original, write_binary_file, read_binary_file, [&] {
        CHECK(fs::file_size(path) == header_size + original.size() * (with_bits ? 32 : 24));
      });
    }
  }

  TEST_CASE("binary: an empty set round-trips as a bare header") {
    temp_dir dir;
    const std::string path = dir.file("empty.boxes");
    REQUIRE_FALSE(write_binary_file(path, box_set{}).has_value());
    CHECK(fs::file_size(path) == header_size);
    box_set back;
    back.push_back(box{});
    REQUIRE_FALSE(read_box_file(path, back).has_value());
    CHECK(back.empty());
  }

  TEST_CASE("binary: byte layout matches docs/embedding.md") {
    temp_dir dir;
    box_set s;
    s.push_back(box{{1, 2, 3}, {4, 5, 6}, 7, 8});
    s.push_back(box{{-1, -2, -3}, {10, 20, 30}, 0x01020304u, 0xffffffffu});
    const std::string path = dir.file("layout.boxes");
    REQUIRE_FALSE(write_binary_file(path, s).has_value());
    const std::string bytes = read_bytes(path);
    REQUIRE(bytes.size() == header_size + 2 * 32);
    CHECK(bytes.substr(0, 8) == "ZBOXES01");
    CHECK(le32(bytes, 8) == 1);   // version
    CHECK(le32(bytes, 12) == 1);  // flags: category/mask present
    CHECK(le64(bytes, 16) == 2);  // count
    const auto f32 = [&](std::size_t offset) { return std::bit_cast<float>(le32(bytes, offset)); };
    // Columns: lo_x, lo_y, lo_z, hi_x, hi_y, hi_z (count float32 each), then category, mask.
    CHECK(f32(24 + 0) == 1.0f);
    CHECK(f32(24 + 4) == -1.0f);
    CHECK(f32(24 + 8) == 2.0f);    // lo_y[0]
    CHECK(f32(24 + 20) == -3.0f);  // lo_z[1]
    CHECK(f32(24 + 24) == 4.0f);   // hi_x[0]
    CHECK(f32(24 + 44) == 30.0f);  // hi_z[1]
    CHECK(le32(bytes, 24 + 48) == 7);
    CHECK(le32(bytes, 24 + 52) == 0x01020304u);
    CHECK(le32(bytes, 24 + 56) == 8);
    CHECK(le32(bytes, 24 + 60) == 0xffffffffu);

    // All category = mask = 1: flag bit 0 clear, no bit columns; the reader fills in 1.
    box_set plain;
    plain.push_back(box{{1, 2, 3}, {4, 5, 6}, 1, 1});
    REQUIRE_FALSE(write_binary_file(path, plain).has_value());
    const std::string plain_bytes = read_bytes(path);
    REQUIRE(plain_bytes.size() == header_size + 24);
    CHECK(le32(plain_bytes, 12) == 0);
    box_set back;
    REQUIRE_FALSE(read_binary_file(path, back).has_value());
    CHECK(back.category == std::vector<std::uint32_t>{1});
    CHECK(back.mask == std::vector<std::uint32_t>{1});
  }

  TEST_CASE("binary: damaged files are rejected with a clear reason") {
    temp_dir dir;
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    const box_set original = random_set(seed, 100, true);
    const std::string good_path = dir.file("good.boxes");
    REQUIRE_FALSE(write_binary_file(good_path, original).has_value());
    const std::string good = read_bytes(good_path);
    const std::string path = dir.file("damaged.boxes");

    const auto expect = [&](const std::string& bytes, const std::string& phrase) {
      write_bytes(path, bytes);
      box_set out;
      out.push_back(box{});
      const auto err = read_binary_file(path, out);
      REQUIRE(err.has_value());
      CAPTURE(err->message);
      CHECK(err->message.find(phrase) != std::string::npos);
      CHECK(err->line == 0);
      CHECK(out.empty());
    };
    expect(good.substr(0, good.size() - 1), "truncated");       // one byte short
    expect(good.substr(0, good.size() - 400), "truncated");     // a column short
    expect(good.substr(0, 12), "truncated");                     // header cut
    expect(good + std::string(1, '\0'), "wrong size");          // trailing byte
    expect(good + std::string(32, '\0'), "wrong size");         // one box too many for the count
    std::string bad_magic = good;
    bad_magic[0] = 'X';
    expect(bad_magic, "bad magic");
    expect("", "bad magic");
    expect("ZBOX", "bad magic");
    std::string version = good;
    put_le32(version, 8, 2);
    expect(version, "unsupported version 2");
    std::string flags = good;
    put_le32(flags, 12, 3);
    expect(flags, "unsupported flags");
    std::string no_bits_flag = good;  // claims no bit columns, but the bytes are there
    put_le32(no_bits_flag, 12, 0);
    expect(no_bits_flag, "wrong size");
    std::string huge_count = good;
    for (std::size_t i = 16; i < 24; ++i) huge_count[i] = '\xff';
    expect(huge_count, "2^32");
  }

  TEST_CASE("binary: a NaN, an infinity or lo > hi is rejected, naming the box") {
    temp_dir dir;
    const std::string path = dir.file("invalid.boxes");
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    const box_set valid = random_set(seed, 50, true);
    const auto expect = [&](std::size_t index, auto&& damage, const std::string& phrase) {
      box_set s = valid;
      damage(s, index);
      REQUIRE_FALSE(write_binary_file(path, s).has_value());  // the writer writes what it is given
      box_set out;
      const auto err = read_box_file(path, out);
      REQUIRE(err.has_value());
      CAPTURE(err->message);
      CHECK(err->message.find("box " + std::to_string(index) + ":") != std::string::npos);
      CHECK(err->message.find(phrase) != std::string::npos);
      CHECK(out.empty());
    };
    expect(3, [](box_set& s, std::size_t i) { s.hi_y[i] = std::numeric_limits<float>::quiet_NaN(); }, "NaN");
    expect(49, [](box_set& s, std::size_t i) { s.lo_x[i] = -std::numeric_limits<float>::infinity(); }, "infinite");
    expect(17, [](box_set& s, std::size_t i) {
      s.lo_z[i] = 5;
      s.hi_z[i] = 4;
    }, "lo.z = 5 > hi.z = 4");
  }

  TEST_CASE("read_box_file picks the format by the magic; a CSV starting otherwise stays CSV") {
    temp_dir dir;
    const std::string csv = dir.file("looks_binary.boxes");  // the extension does not matter
    write_bytes(csv, "0,0,0,1,1,1\n");
    box_set s;
    REQUIRE_FALSE(read_box_file(csv, s).has_value());
    CHECK(s.size() == 1);
    // A file that starts with the magic is binary, and a damaged one is reported as binary.
    write_bytes(csv, "ZBOXES01junk");
    const auto err = read_box_file(csv, s);
    REQUIRE(err.has_value());
    CHECK(err->message.find("truncated") != std::string::npos);
    // The same bytes through the CSV reader are a CSV error on line 1.
    const auto csv_err = read_csv_file(csv, s);
    REQUIRE(csv_err.has_value());
    CHECK(csv_err->line == 1);
  }

  TEST_CASE("writers replace an existing file and leave no temporary behind") {
    temp_dir dir;
    const std::string path = dir.file("replace.boxes");
    write_bytes(path, "old contents");
    box_set s;
    s.push_back(box{{0, 0, 0}, {1, 1, 1}, 2, 3});
    REQUIRE_FALSE(write_binary_file(path, s).has_value());
    box_set back;
    REQUIRE_FALSE(read_box_file(path, back).has_value());
    CHECK(same_sets(s, back));
    CHECK_FALSE(fs::exists(path + ".tmp"));
  }
}
