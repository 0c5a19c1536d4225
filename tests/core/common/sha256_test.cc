#include "core/common/sha256.h"

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "gtest/gtest.h"

namespace interslice {
namespace {

// Artifacts are hashed on several threads: each digest must land in its own
// file's slot whatever the order of completion, and an unreadable file gives
// an error in its slot only.
TEST(Sha256OfFilesTest, EachDigestInItsSlotOnAnyThreadCount) {
  const std::filesystem::path dir =
      std::filesystem::path(::testing::TempDir()) / "sha256-of-files";
  std::filesystem::create_directories(dir);
  std::vector<std::string> paths;
  for (int n = 0; n < 7; ++n) {
    paths.push_back((dir / ("f" + std::to_string(n))).string());
    // Sizes in no particular order, so largest-first changes the order.
    std::ofstream(paths.back(), std::ios::binary)
        << std::string(static_cast<size_t>((n * 37 % 7) * 100000 + n),
                       static_cast<char>('a' + n));
  }
  paths.insert(paths.begin() + 3, (dir / "missing").string());
  for (int threads : {0, 1, 2, 5, 16}) {
    const auto shas = Sha256OfFiles(paths, threads);
    ASSERT_EQ(shas.size(), paths.size());
    for (size_t n = 0; n < paths.size(); ++n) {
      const auto one = Sha256OfFile(paths[n]);
      ASSERT_EQ(shas[n].ok(), one.ok()) << paths[n];
      if (one.ok()) {
        EXPECT_EQ(*shas[n], *one) << paths[n] << " threads " << threads;
      }
    }
    EXPECT_FALSE(shas[3].ok());
  }
  // The digest itself, for a known input ("abc", FIPS 180-2 appendix B.1).
  const std::string abc = (dir / "abc").string();
  std::ofstream(abc, std::ios::binary) << "abc";
  EXPECT_EQ(HexString(*Sha256OfFiles({abc}, 2)[0]),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace interslice
