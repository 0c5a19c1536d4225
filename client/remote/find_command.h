// `interslice find --pacs PEER`: what a DICOM peer of the server holds
// (C-FIND by the server), for `submit --pacs PEER --study UID --series UID`.
#ifndef INTERSLICE_CLIENT_REMOTE_FIND_COMMAND_H_
#define INTERSLICE_CLIENT_REMOTE_FIND_COMMAND_H_

#include <string>

#include "client/grpc_channel.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client::remote {

// The peer and the keys.
struct FindArguments {
  std::string peer;
  std::string patient_id;
  std::string study_date;
  std::string modality;
  std::string accession;
  int max_studies = 0;
};

CLI::App* RegisterFind(CLI::App& app, FindArguments& args,
                       ConnectionOptions& connection);
// Studies, then their series, one per line with their UIDs (for
// `submit --pacs PEER --study UID --series UID`). Text from the PACS reaches
// the terminal without control characters.
int RunFind(const Connection& connection, const FindArguments& args);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_FIND_COMMAND_H_
