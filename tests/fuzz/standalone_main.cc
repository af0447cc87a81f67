// Fuzz driver for compilers without libFuzzer (gcc): replays every file of a corpus directory
// through LLVMFuzzerTestOneInput, then runs a fixed number of deterministic mutations of them
// (bit flips, byte edits, insertions of interesting tokens, deletions, duplications,
// truncation, splicing two inputs). Fixed seed, so a finding reproduces exactly.
//   usage: <target> CORPUS_DIR [ITERATIONS=20000] [SEED=1]
// A crash or an exception other than rs::Error (which the target catches) writes the input to
// crash-<target>-<n> in the working directory and fails.
#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);

namespace {

constexpr size_t kMaxInput = 64 * 1024;

// The input being run, for the crash handler (plain globals: read from a signal handler).
const uint8_t* g_current = nullptr;
size_t g_current_size = 0;
char g_crash_path[512] = "crash-input";

void WriteCrashInput() {
  const int fd = open(g_crash_path, O_WRONLY | O_CREAT | O_TRUNC, 0644);
  if (fd >= 0) {
    size_t done = 0;
    while (done < g_current_size) {
      const ssize_t n = write(fd, g_current + done, g_current_size - done);
      if (n <= 0) break;
      done += static_cast<size_t>(n);
    }
    close(fd);
  }
}

void OnSignal(int sig) {
  WriteCrashInput();
  static const char kMsg[] = "fuzz: crash (signal); input written to ";
  [[maybe_unused]] ssize_t r = write(2, kMsg, sizeof(kMsg) - 1);
  r = write(2, g_crash_path, strlen(g_crash_path));
  r = write(2, "\n", 1);
  std::signal(sig, SIG_DFL);
  std::raise(sig);
}

// splitmix64: deterministic everywhere.
struct Rng {
  uint64_t state;
  uint64_t Next() {
    uint64_t z = (state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  size_t Below(size_t n) { return n == 0 ? 0 : static_cast<size_t>(Next() % n); }
};

// Tokens that tend to reach edge cases in text formats (numbers, separators, keywords).
const char* const kTokens[] = {"0",
                               "-1",
                               "1",
                               "-0",
                               "nan",
                               "inf",
                               "-inf",
                               "1e39",
                               "1e-45",
                               "4294967296",
                               "2147483648",
                               "-2147483649",
                               "99999999999",
                               "0x10",
                               " ",
                               "\t",
                               "\n",
                               "\r\n",
                               "\r",
                               "/",
                               "//",
                               "{",
                               "}",
                               "[",
                               "]",
                               "\"",
                               ",",
                               ":",
                               "null",
                               "true",
                               "1.5",
                               "[0,0,0]",
                               "\"name\"",
                               "f ",
                               "v ",
                               "vt ",
                               "vn ",
                               "usemtl ",
                               "mtllib ",
                               "g ",
                               "o ",
                               "s off",
                               "element ",
                               "property ",
                               "list ",
                               "uchar ",
                               "int ",
                               "float ",
                               "end_header\n",
                               "format binary_little_endian 1.0\n",
                               "format binary_big_endian 1.0\n",
                               "\xff\xff\xff\xff",
                               "\x00",
                               "#",
                               "/*",
                               "*/",
                               "\xef\xbb\xbf"};

std::vector<uint8_t> Mutate(const std::vector<uint8_t>& base, const std::vector<uint8_t>& other,
                            Rng& rng) {
  std::vector<uint8_t> d = base;
  const int steps = 1 + static_cast<int>(rng.Below(4));
  for (int s = 0; s < steps; ++s) {
    switch (rng.Below(9)) {
      case 0:  // flip a bit
        if (!d.empty()) d[rng.Below(d.size())] ^= static_cast<uint8_t>(1u << rng.Below(8));
        break;
      case 1:  // set a byte
        if (!d.empty()) d[rng.Below(d.size())] = static_cast<uint8_t>(rng.Next());
        break;
      case 2: {  // insert a random byte
        d.insert(d.begin() + static_cast<std::ptrdiff_t>(rng.Below(d.size() + 1)),
                 static_cast<uint8_t>(rng.Next()));
        break;
      }
      case 3:
      case 4: {  // insert or overwrite with an interesting token
        const char* tok = kTokens[rng.Below(std::size(kTokens))];
        const size_t len = std::max<size_t>(1, std::strlen(tok));  // "\x00" inserts one NUL
        const size_t at = rng.Below(d.size() + 1);
        if (rng.Below(2) == 0 || at + len > d.size()) {
          d.insert(d.begin() + static_cast<std::ptrdiff_t>(at), tok, tok + len);
        } else {
          std::copy(tok, tok + len, d.begin() + static_cast<std::ptrdiff_t>(at));
        }
        break;
      }
      case 5: {  // delete a range
        if (d.empty()) break;
        const size_t at = rng.Below(d.size());
        const size_t len = 1 + rng.Below(std::min<size_t>(16, d.size() - at));
        d.erase(d.begin() + static_cast<std::ptrdiff_t>(at),
                d.begin() + static_cast<std::ptrdiff_t>(at + len));
        break;
      }
      case 6: {  // duplicate a range (repeats lines, grows counts)
        if (d.empty()) break;
        const size_t at = rng.Below(d.size());
        const size_t len = 1 + rng.Below(std::min<size_t>(64, d.size() - at));
        const std::vector<uint8_t> piece(d.begin() + static_cast<std::ptrdiff_t>(at),
                                         d.begin() + static_cast<std::ptrdiff_t>(at + len));
        d.insert(d.begin() + static_cast<std::ptrdiff_t>(rng.Below(d.size() + 1)), piece.begin(),
                 piece.end());
        break;
      }
      case 7:  // truncate
        d.resize(rng.Below(d.size() + 1));
        break;
      case 8: {  // splice: a prefix of this input and a suffix of another
        const size_t cut_a = rng.Below(d.size() + 1);
        const size_t cut_b = rng.Below(other.size() + 1);
        d.resize(cut_a);
        d.insert(d.end(), other.begin() + static_cast<std::ptrdiff_t>(cut_b), other.end());
        break;
      }
    }
    if (d.size() > kMaxInput) d.resize(kMaxInput);
  }
  return d;
}

bool Run(const std::vector<uint8_t>& input, const std::string& what) {
  g_current = input.data();
  g_current_size = input.size();
  try {
    LLVMFuzzerTestOneInput(input.data(), input.size());
  } catch (const std::exception& e) {
    WriteCrashInput();
    std::fprintf(stderr, "fuzz: FINDING in %s: uncaught exception: %s\n  input written to %s\n",
                 what.c_str(), e.what(), g_crash_path);
    return false;
  } catch (...) {
    WriteCrashInput();
    std::fprintf(stderr, "fuzz: FINDING in %s: uncaught non-std exception\n  input written to %s\n",
                 what.c_str(), g_crash_path);
    return false;
  }
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s CORPUS_DIR [ITERATIONS] [SEED]\n", argv[0]);
    return 2;
  }
  const std::string target = std::filesystem::path(argv[0]).filename().string();
  std::snprintf(g_crash_path, sizeof(g_crash_path), "crash-%s", target.c_str());
  const long iterations = argc > 2 ? std::atol(argv[2]) : 20000;
  Rng rng{argc > 3 ? std::strtoull(argv[3], nullptr, 10) : 1};
  for (int sig : {SIGSEGV, SIGABRT, SIGFPE, SIGBUS, SIGILL}) std::signal(sig, OnSignal);

  // Corpus, sorted by name so the run does not depend on directory order.
  std::vector<std::filesystem::path> files;
  for (const auto& entry : std::filesystem::directory_iterator(argv[1])) {
    if (entry.is_regular_file()) files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  if (files.empty()) {
    std::fprintf(stderr, "fuzz: no corpus files in %s\n", argv[1]);
    return 2;
  }
  std::vector<std::vector<uint8_t>> corpus;
  for (const auto& f : files) {
    std::ifstream in(f, std::ios::binary);
    corpus.emplace_back(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
    if (!Run(corpus.back(), f.string())) return 1;
  }
  const auto start = std::chrono::steady_clock::now();
  // Mutants are mostly of corpus files; one in four builds on a recent mutant for depth.
  std::vector<std::vector<uint8_t>> recent;
  for (long i = 0; i < iterations; ++i) {
    const bool deepen = !recent.empty() && rng.Below(4) == 0;
    const std::vector<uint8_t>& base =
        deepen ? recent[rng.Below(recent.size())] : corpus[rng.Below(corpus.size())];
    const std::vector<uint8_t>& other = corpus[rng.Below(corpus.size())];
    std::vector<uint8_t> input = Mutate(base, other, rng);
    if (!Run(input, "mutation " + std::to_string(i))) return 1;
    if (recent.size() < 64) {
      recent.push_back(std::move(input));
    } else {
      recent[rng.Below(recent.size())] = std::move(input);
    }
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf("fuzz %s: %zu corpus files replayed, %ld mutations in %.2f s, no findings\n",
              target.c_str(), corpus.size(), iterations, seconds);
  return 0;
}
