// The configuration the project ships starts a server as shipped (issue 25):
// every `interslice-server` command of the README and docs/dicom-node.md is
// run as written (its heredoc files written first), and the compose stack's
// command with deploy/config; each must start and stop cleanly. Every YAML
// file under docs/examples and deploy/config must be used by one of them, so
// a new example file cannot be left untested.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/server_process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"
#include "yaml-cpp/yaml.h"

namespace interslice::testing {
namespace {

namespace fs = std::filesystem;

const std::string kSource = ::interslice::testing::SourceDir();

std::string ReadText(const std::string& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

// One shell command of a document, with the files its block wrote by
// heredoc before it (`cat > NAME <<'END' ... END`).
struct DocumentedCommand {
  std::string where;  // "README.md:367", for messages
  int block = 0;      // which ```sh block of its document
  std::vector<std::string> argv;
  std::map<std::string, std::string> heredocs;  // file name -> content
  // The DCMTK commands (echoscu, storescu) that follow it in its block.
  std::vector<std::vector<std::string>> dcmtk_commands;
};

// The `interslice-server` commands of the ```sh blocks of `doc`: `\`
// continuations joined, a trailing `&` and `# comment` dropped. Words are
// split on spaces (the documented commands quote nothing).
std::vector<DocumentedCommand> ServerCommands(const std::string& doc) {
  std::vector<DocumentedCommand> commands;
  const std::vector<std::string> lines =
      absl::StrSplit(ReadText(kSource + "/" + doc), '\n');
  bool in_block = false;
  int block = 0;
  std::map<std::string, std::string> heredocs;
  for (size_t i = 0; i < lines.size(); ++i) {
    const std::string& line = lines[i];
    if (absl::StartsWith(line, "```")) {
      in_block = !in_block && absl::StartsWith(line, "```sh");
      ++block;
      heredocs.clear();
      continue;
    }
    if (!in_block) continue;
    if (absl::StartsWith(line, "cat > ") && absl::StrContains(line, "<<'")) {
      const std::vector<std::string> words = absl::StrSplit(line, ' ');
      const std::string file = words[2];
      std::string end(absl::StripPrefix(words[3], "<<'"));
      end = std::string(absl::StripSuffix(end, "'"));
      std::string body;
      for (++i; i < lines.size() && lines[i] != end; ++i) {
        body += lines[i] + "\n";
      }
      heredocs[file] = body;
      continue;
    }
    if ((absl::StartsWith(line, "storescu ") ||
         absl::StartsWith(line, "echoscu ")) &&
        !commands.empty() && commands.back().block == block) {
      std::vector<std::string> argv;
      for (absl::string_view word :
           absl::StrSplit(line, ' ', absl::SkipWhitespace())) {
        if (absl::StartsWith(word, "#")) break;
        argv.emplace_back(word);
      }
      commands.back().dcmtk_commands.push_back(argv);
      continue;
    }
    if (!absl::StartsWith(line, "interslice-server ")) continue;
    DocumentedCommand command;
    command.where = absl::StrCat(doc, ":", i + 1);
    command.block = block;
    command.heredocs = heredocs;
    std::string joined = line;
    while (absl::EndsWith(joined, "\\") && i + 1 < lines.size()) {
      joined.pop_back();
      joined += lines[++i];
    }
    for (absl::string_view word :
         absl::StrSplit(joined, ' ', absl::SkipWhitespace())) {
      if (absl::StartsWith(word, "#")) break;
      if (word == "&") continue;
      command.argv.emplace_back(word);
    }
    commands.push_back(std::move(command));
  }
  return commands;
}

// Starts the server with `argv` (argv[0] is the program, dropped) in place
// of the deployment's addresses and spool: --listen, --dicom-listen and
// --metrics-listen on free loopback ports, --spool in `dir`. Relative paths
// are the repository's (docs/..., deploy/...) unless the command's block
// wrote them. Records which repository files it read in `used`.
void ExpectStarts(const std::string& where, std::vector<std::string> argv,
                  const std::map<std::string, std::string>& heredocs,
                  std::set<std::string>* used,
                  const std::function<void(ServerProcess&)>& then = nullptr) {
  SCOPED_TRACE(where);
  TempDir dir;
  std::vector<std::string> extra;
  for (size_t i = 1; i < argv.size(); ++i) {
    std::string flag = argv[i], value;
    const size_t eq = flag.find('=');
    if (eq != std::string::npos) {
      value = flag.substr(eq + 1);
      flag = flag.substr(0, eq);
    } else if (i + 1 < argv.size() && !absl::StartsWith(argv[i + 1], "--")) {
      value = argv[++i];
    }
    // ServerProcess passes these itself: a free port, the test's spool.
    if (flag == "--listen" || flag == "--spool") continue;
    if (flag == "--dicom-listen" || flag == "--metrics-listen") {
      value = "127.0.0.1:0";
    }
    if (flag == "--dicom-peers" || flag == "--rules") {
      if (heredocs.count(value) != 0) {
        std::ofstream(dir / value) << heredocs.at(value);
        value = dir / value;
      } else {
        const std::string path = (fs::path(kSource) / value).string();
        EXPECT_TRUE(fs::exists(path)) << flag << " " << value;
        used->insert(fs::weakly_canonical(path).string());
        value = path;
      }
    }
    extra.push_back(flag);
    if (!value.empty()) extra.push_back(value);
  }
  ServerProcess server({.spool = dir / "spool", .extra = extra});
  ASSERT_TRUE(server.Start()) << "refused: " << absl::StrJoin(argv, " ");
  if (then) then(server);
  EXPECT_EQ(server.Stop(), 0) << server.Log();
}

TEST(ShippedConfigTest, EveryDocumentedCommandAndExampleFileStartsAServer) {
  std::set<std::string> used;
  int commands = 0;
  for (const char* doc : {"README.md", "docs/dicom-node.md"}) {
    for (const DocumentedCommand& c : ServerCommands(doc)) {
      ExpectStarts(c.where, c.argv, c.heredocs, &used);
      ++commands;
    }
  }
  // The compose stack's command, with its variables at their defaults and
  // its config folder (deploy/config) where it mounts it.
  const YAML::Node compose = YAML::LoadFile(kSource + "/deploy/compose.yaml");
  std::vector<std::string> argv = {"interslice-server"};
  for (const YAML::Node& word : compose["services"]["interslice"]["command"]) {
    std::string text = word.as<std::string>();
    // ${NAME:-default} -> default
    for (size_t at; (at = text.find("${")) != std::string::npos;) {
      const size_t close = text.find('}', at);
      const size_t dash = text.find(":-", at);
      ASSERT_NE(close, std::string::npos) << text;
      ASSERT_LT(dash, close) << text;
      text = text.substr(0, at) + text.substr(dash + 2, close - dash - 2) +
             text.substr(close + 1);
    }
    if (absl::StartsWith(text, "/etc/interslice/")) {
      text = "deploy/config/" + text.substr(strlen("/etc/interslice/"));
    }
    argv.push_back(text);
  }
  ExpectStarts("deploy/compose.yaml", argv, {}, &used);
  ++commands;
  // At least the README's, the node doc's and the compose stack's.
  EXPECT_GE(commands, 4);

  for (const char* folder : {"docs/examples", "deploy/config"}) {
    for (const auto& entry : fs::directory_iterator(kSource + "/" + folder)) {
      if (entry.path().extension() != ".yaml") continue;
      EXPECT_EQ(used.count(fs::weakly_canonical(entry.path()).string()), 1u)
          << entry.path() << " is shipped but no documented command starts "
          << "a server with it";
    }
  }
}

// The README's first block as written: the server with the shipped
// examples, then its storescu of the phantom (to the server's port), makes
// the job of the examples' ct-bone rule (the phantom is "STD BRAIN 5MM").
TEST(ShippedConfigTest, ReadmeStorescuOfThePhantomMakesTheExampleRulesJob) {
  const std::vector<DocumentedCommand> commands = ServerCommands("README.md");
  // The "Next to a PACS" one: the server with the example rules.
  auto with_rules = std::find_if(
      commands.begin(), commands.end(), [](const DocumentedCommand& c) {
        return std::find(c.argv.begin(), c.argv.end(),
                         "docs/examples/rules.yaml") != c.argv.end();
      });
  ASSERT_NE(with_rules, commands.end());
  const DocumentedCommand& first = *with_rules;
  ASSERT_FALSE(first.dcmtk_commands.empty()) << first.where;
  std::set<std::string> used;
  ExpectStarts(
      first.where, first.argv, first.heredocs, &used,
      [&](ServerProcess& server) {
        for (std::vector<std::string> argv : first.dcmtk_commands) {
          std::vector<std::string> expanded = {"/usr/bin/" + argv[0]};
          for (size_t i = 1; i < argv.size(); ++i) {
            std::string word = argv[i];
            if (word == "11112") {
              word = std::to_string(server.dicom_port());
            }
            const size_t star = word.find("/*");
            if (star == std::string::npos) {
              expanded.push_back(word);
              continue;
            }
            // A shell glob "DIR/*SUFFIX": the files, sorted.
            const std::string folder = kSource + "/" + word.substr(0, star);
            const std::string suffix = word.substr(star + 2);
            std::vector<std::string> files;
            for (const auto& e : fs::directory_iterator(folder)) {
              if (absl::EndsWith(e.path().string(), suffix)) {
                files.push_back(e.path().string());
              }
            }
            std::sort(files.begin(), files.end());
            EXPECT_FALSE(files.empty()) << word;
            expanded.insert(expanded.end(), files.begin(), files.end());
          }
          CommandResult r = RunCommand(expanded, 300);
          EXPECT_EQ(r.exit_code, 0)
              << absl::StrJoin(argv, " ") << ": " << r.err;
        }
        EXPECT_TRUE(WaitFor(
            [&] {
              return absl::StrContains(server.Log(), "made by rule ct-bone");
            },
            std::chrono::seconds(120), std::chrono::milliseconds(200)))
            << server.Log();
      });
}

}  // namespace
}  // namespace interslice::testing
