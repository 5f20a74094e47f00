// Runs a policy exported with `pi0-torch export --format pt2`: loads the AOTInductor package, builds inputs of the
// shapes its metadata records (`pi0_torch.deploy.export`), runs one chunk and prints the actions.
//
//   run_policy MODEL.pt2 [TOKEN_ID ...]
//
// The inputs here are stand-ins: black frames with every camera shown, a prompt of the given token ids (default: 2, the
// beginning-of-sequence token, and 108, "\n" in PaliGemma's vocabulary), a zero state and zero noise (the most likely
// chunk). A robot's node fills them from its cameras, its SentencePiece tokenizer (the folder's tokenizer.model, with
// the prompt format of deploy.json) and its joint readings, and draws standard normal noise times the folder's scale.
#include <torch/csrc/inductor/aoti_package/model_package_loader.h>
#include <torch/torch.h>

#include <iostream>
#include <sstream>
#include <string>
#include <vector>

namespace {

std::vector<int64_t> parse_shape(const std::string& text) {
  std::vector<int64_t> shape;
  std::stringstream stream(text);
  std::string size;
  while (std::getline(stream, size, ',')) shape.push_back(std::stoll(size));
  return shape;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::cerr << "usage: run_policy MODEL.pt2 [TOKEN_ID ...]\n";
    return 2;
  }
  try {
    torch::inductor::AOTIModelPackageLoader loader(argv[1]);
    auto metadata = loader.get_metadata();
    if (metadata.find("images.shape") == metadata.end()) {
      std::cerr << argv[1] << ": no pi0-torch input metadata (export it with pi0-torch export --format pt2)\n";
      return 1;
    }
    const torch::Device device(metadata.count("device") ? metadata["device"] : std::string("cpu"));  // compiled for
    auto images = torch::zeros(parse_shape(metadata["images.shape"]), torch::kUInt8);            // [B, C, H, W, 3]
    auto image_masks = torch::ones(parse_shape(metadata["image_masks.shape"]), torch::kBool);     // [B, C]
    auto ids_shape = parse_shape(metadata["input_ids.shape"]);                                    // [B, L]
    auto input_ids = torch::zeros(ids_shape, torch::kInt64);
    auto attention_mask = torch::zeros(ids_shape, torch::kBool);
    std::vector<int64_t> tokens = {2, 108};
    if (argc > 2) {
      tokens.clear();
      for (int i = 2; i < argc; ++i) tokens.push_back(std::stoll(argv[i]));
    }
    for (size_t t = 0; t < tokens.size() && static_cast<int64_t>(t) < ids_shape[1]; ++t) {
      input_ids.index_put_({torch::indexing::Slice(), static_cast<int64_t>(t)}, tokens[t]);
      attention_mask.index_put_({torch::indexing::Slice(), static_cast<int64_t>(t)}, true);
    }
    auto state = torch::zeros(parse_shape(metadata["state.shape"]), torch::kFloat32);             // [B, state dims]
    auto noise = torch::zeros(parse_shape(metadata["noise.shape"]), torch::kFloat32);             // [B, horizon, A]
    std::vector<torch::Tensor> inputs = {images, image_masks, input_ids, attention_mask, state, noise};
    for (auto& input : inputs) input = input.to(device);
    auto actions = loader.run(inputs)[0].to(torch::kCPU);                                         // [B, horizon, dims]
    std::cout << "actions " << actions.sizes() << "\n" << actions[0] << "\n";
  } catch (const std::exception& error) {
    std::cerr << "run_policy: " << error.what() << "\n";
    return 1;
  }
  return 0;
}
