#include "job/errors.h"

#include "absl/strings/cord.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "job/options.h"

namespace interslice::job {
namespace {

constexpr absl::string_view kKeyPayload = "interslice.job/option-key";

template <typename Options>
absl::string_view WireName(std::span<const OptionDef<Options>> table,
                           absl::string_view key) {
  const OptionDef<Options>* def = FindOption(table, key);
  return def != nullptr ? def->wire : absl::string_view();
}

}  // namespace

absl::Status OptionError(absl::string_view key, absl::string_view message) {
  absl::Status status = absl::InvalidArgumentError(
      absl::StrCat(std::string(key), ": ", std::string(message)));
  status.SetPayload(std::string(kKeyPayload), absl::Cord(std::string(key)));
  return status;
}

std::optional<std::string> ErrorOptionKey(const absl::Status& status) {
  const auto key = status.GetPayload(std::string(kKeyPayload));
  if (!key.has_value()) return std::nullopt;
  return std::string(*key);
}

std::string ErrorMessageWithoutKey(const absl::Status& status) {
  std::string message(status.message());
  const std::optional<std::string> key = ErrorOptionKey(status);
  if (key.has_value()) {
    const std::string prefix = absl::StrCat(*key, ": ");
    if (absl::StartsWith(message, prefix)) return message.substr(prefix.size());
  }
  return message;
}

absl::Status ForDoor(const absl::Status& status, ErrorDoor door, bool fill) {
  const std::optional<std::string> key = ErrorOptionKey(status);
  if (!key.has_value()) return status;
  std::string field;
  switch (door) {
    case ErrorDoor::kCommandLine:
      field = CommandLineName(*key);
      break;
    case ErrorDoor::kRulesJob:
      field = absl::StrCat("job.", *key);
      break;
    case ErrorDoor::kRulesFill:
      field = absl::StrCat("fill.", *key);
      break;
    case ErrorDoor::kWire: {
      absl::string_view wire = fill
                                   ? WireName(FillOptionTable(), *key)
                                   : WireName(InterpolationOptionTable(), *key);
      if (wire.empty()) {
        wire = fill ? WireName(InterpolationOptionTable(), *key)
                    : WireName(FillOptionTable(), *key);
      }
      field = wire.empty() ? absl::StrCat("spec.", *key) : std::string(wire);
      break;
    }
  }
  absl::Status out(status.code(),
                   absl::StrCat(field, ": ", ErrorMessageWithoutKey(status)));
  status.ForEachPayload(
      [&out](absl::string_view url, const absl::Cord& payload) {
        out.SetPayload(url, payload);
      });
  return out;
}

}  // namespace interslice::job
