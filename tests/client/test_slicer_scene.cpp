// scene.mrml parsed back with expat: the node types Slicer needs, every
// reference resolving, every file present, the preop volume (only) under the
// field's grid transform, names and colours from the label table (models and
// the label map's colour table), model storage declaring RAS like the files.
#include <expat.h>
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>

#include "mesh/vtk_io.h"
#include "slicer_scene.h"

namespace brainshift::cli {
namespace {
namespace fs = std::filesystem;

struct Node {
  std::string tag;
  std::map<std::string, std::string> attrs;
  std::string at(const std::string& key) const {
    auto it = attrs.find(key);
    return it == attrs.end() ? "" : it->second;
  }
  // "display:ID;storage:ID;" -> ID of the role, "" when absent.
  std::string ref(const std::string& role) const {
    std::stringstream s(at("references"));
    std::string item;
    while (std::getline(s, item, ';'))
      if (item.rfind(role + ":", 0) == 0) return item.substr(role.size() + 1);
    return "";
  }
};

struct Scene {
  std::string root;
  std::vector<Node> nodes;
  const Node* by_id(const std::string& id) const {
    for (const auto& n : nodes)
      if (n.at("id") == id) return &n;
    return nullptr;
  }
  std::vector<const Node*> tagged(const std::string& tag) const {
    std::vector<const Node*> out;
    for (const auto& n : nodes)
      if (n.tag == tag) out.push_back(&n);
    return out;
  }
};

Scene parse(const fs::path& file) {
  std::ifstream in(file);
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  Scene scene;
  XML_Parser p = XML_ParserCreate(nullptr);
  XML_SetUserData(p, &scene);
  XML_SetStartElementHandler(p, [](void* data, const XML_Char* name, const XML_Char** atts) {
    auto* s = static_cast<Scene*>(data);
    if (s->root.empty()) {
      s->root = name;
      return;
    }
    Node n{name, {}};
    for (int i = 0; atts[i]; i += 2) n.attrs[atts[i]] = atts[i + 1];
    s->nodes.push_back(n);
  });
  const bool ok = XML_Parse(p, text.data(), static_cast<int>(text.size()), 1) == XML_STATUS_OK;
  const std::string error = ok ? "" : XML_ErrorString(XML_GetErrorCode(p));
  XML_ParserFree(p);
  if (!ok) throw std::runtime_error(file.string() + ": not well-formed XML: " + error);
  return scene;
}

void touch(const fs::path& p) {
  fs::create_directories(p.parent_path());
  std::ofstream(p) << "x";
}

class SlicerScene : public ::testing::Test {
 protected:
  void SetUp() override {
    dir = fs::temp_directory_path() / ("brainshift_scene_" + std::to_string(::getpid()));
    fs::remove_all(dir);
    for (const char* f : {"field.h5", "warped_image.nii.gz", "warped_labels.nii.gz", "preop_image.nii.gz",
                          "intraop_image.nii"})
      touch(dir / f);
    // Real models, as pull writes them (SPACE = RAS in the file).
    TriSurface s;
    s.vertices_mm = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
    s.triangles = {{0, 2, 1}, {0, 1, 3}, {0, 3, 2}, {1, 2, 3}};
    fs::create_directories(dir / "models");
    for (const char* name : {"brain", "tumor", "a&b<arcuate>"}) write_vtp(dir / "models" / (std::string(name) + ".vtp"), s);
    contents.preop_image = "preop_image.nii.gz";
    contents.intraop_image = "intraop_image.nii";
    contents.labels = {{1, "brain", {40, 220, 60}, true},
                       {2, "ventricles", {0, 200, 255}, false},  // no model file: no model node
                       {4, "tumor", {255, 230, 0}, false},
                       {7, "a&b<arcuate>", {150, 90, 255}, false}};
  }
  void TearDown() override { fs::remove_all(dir); }
  fs::path dir;
  SceneContents contents;
};

TEST_F(SlicerScene, NodesReferencesFilesFramesNamesAndColours) {
  write_slicer_scene(dir, contents);
  const Scene scene = parse(dir / kSceneFile);
  EXPECT_EQ(scene.root, "MRML");
  // Every reference resolves to a node of the scene; every file exists.
  for (const auto& n : scene.nodes) {
    for (const char* role : {"display", "storage", "transform"}) {
      const std::string id = n.ref(role);
      if (!id.empty()) {
        EXPECT_NE(scene.by_id(id), nullptr) << n.tag << " " << role << " " << id;
      }
    }
    if (!n.at("colorNodeID").empty() && n.at("colorNodeID") != "vtkMRMLColorTableNodeGrey") {
      EXPECT_NE(scene.by_id(n.at("colorNodeID")), nullptr);
    }
    if (!n.at("fileName").empty()) {
      EXPECT_TRUE(fs::is_regular_file(dir / n.at("fileName"))) << n.at("fileName");
    }
  }
  // One grid transform, read from field.h5.
  const auto transforms = scene.tagged("GridTransform");
  ASSERT_EQ(transforms.size(), 1u);
  const std::string field_id = transforms[0]->at("id");
  EXPECT_EQ(scene.by_id(transforms[0]->ref("storage"))->at("fileName"), "field.h5");
  EXPECT_EQ(scene.by_id(transforms[0]->ref("storage"))->tag, "TransformStorage");
  // Volumes: the preop under the field, the intraop-frame ones not.
  std::map<std::string, const Node*> volumes;
  for (const Node* v : scene.tagged("Volume")) volumes[scene.by_id(v->ref("storage"))->at("fileName")] = v;
  ASSERT_EQ(volumes.size(), 3u);
  EXPECT_EQ(volumes.at("preop_image.nii.gz")->ref("transform"), field_id);
  EXPECT_EQ(volumes.at("intraop_image.nii")->ref("transform"), "");
  EXPECT_EQ(volumes.at("warped_image.nii.gz")->ref("transform"), "");
  for (const auto& [file, v] : volumes) EXPECT_EQ(scene.by_id(v->ref("storage"))->tag, "VolumeArchetypeStorage");
  // The label map: its display's colour table is the label table.
  const auto label_maps = scene.tagged("LabelMapVolume");
  ASSERT_EQ(label_maps.size(), 1u);
  EXPECT_EQ(label_maps[0]->ref("transform"), "");
  EXPECT_EQ(scene.by_id(label_maps[0]->ref("storage"))->at("fileName"), "warped_labels.nii.gz");
  const Node* display = scene.by_id(label_maps[0]->ref("display"));
  EXPECT_EQ(display->tag, "LabelMapVolumeDisplay");
  const Node* table = scene.by_id(display->at("colorNodeID"));
  ASSERT_NE(table, nullptr);
  EXPECT_EQ(table->tag, "ColorTable");
  const Node* table_storage = scene.by_id(table->ref("storage"));
  EXPECT_EQ(table_storage->tag, "ColorTableStorage");
  std::ifstream ctbl(dir / table_storage->at("fileName"));
  std::map<int, std::string> rows;
  for (std::string line; std::getline(ctbl, line);)
    if (!line.empty() && line[0] != '#') rows[std::stoi(line)] = line;
  EXPECT_EQ(rows.at(0), "0 background 0 0 0 0");
  EXPECT_EQ(rows.at(1), "1 brain 40 220 60 255");
  EXPECT_EQ(rows.at(2), "2 ventricles 0 200 255 255");
  EXPECT_EQ(rows.at(4), "4 tumor 255 230 0 255");
  EXPECT_EQ(rows.size(), 5u);
  // Models: one per label with a file, named and coloured by the table,
  // stored as RAS like the files themselves say.
  const auto models = scene.tagged("Model");
  ASSERT_EQ(models.size(), 3u);
  for (const Node* m : models) {
    const auto label = std::find_if(contents.labels.begin(), contents.labels.end(),
                                    [&](const SceneLabel& l) { return l.name == m->at("name"); });
    ASSERT_NE(label, contents.labels.end()) << m->at("name");
    EXPECT_EQ(m->ref("transform"), "");  // already in the intraop frame
    const Node* storage = scene.by_id(m->ref("storage"));
    EXPECT_EQ(storage->tag, "ModelStorage");
    EXPECT_EQ(storage->at("coordinateSystem"), "RAS");
    EXPECT_EQ(storage->at("fileName"), "models/" + label->name + ".vtp");
    std::ifstream vtp(dir / storage->at("fileName"));
    EXPECT_EQ(vtk_space(std::string((std::istreambuf_iterator<char>(vtp)), std::istreambuf_iterator<char>())), "RAS");
    std::stringstream colour(scene.by_id(m->ref("display"))->at("color"));
    for (int c = 0; c < 3; ++c) {
      double v = -1;
      colour >> v;
      EXPECT_NEAR(v, label->colour[c] / 255.0, 1e-6) << label->name;
    }
    EXPECT_EQ(scene.by_id(m->ref("display"))->at("opacity"), label->outer ? "0.3" : "1");
  }
}

TEST_F(SlicerScene, WithoutLocalImagesOnlyThePulledOutputs) {
  contents.preop_image.reset();
  contents.intraop_image.reset();
  write_slicer_scene(dir, contents);
  const Scene scene = parse(dir / kSceneFile);
  EXPECT_EQ(scene.tagged("Volume").size(), 1u);  // the warped preop T1
  EXPECT_EQ(scene.tagged("GridTransform").size(), 1u);
}

TEST_F(SlicerScene, AnAutomaticSegmentationIsListedWithTheLabelTable) {
  touch(dir / "intraop_labels.nii.gz");
  touch(dir / "segmentation_confidence.nii.gz");
  write_slicer_scene(dir, contents);
  const Scene scene = parse(dir / kSceneFile);
  std::map<std::string, const Node*> label_maps;
  for (const Node* v : scene.tagged("LabelMapVolume")) label_maps[scene.by_id(v->ref("storage"))->at("fileName")] = v;
  ASSERT_EQ(label_maps.size(), 2u);
  const Node* seg = label_maps.at("intraop_labels.nii.gz");
  EXPECT_EQ(scene.by_id(seg->ref("display"))->at("colorNodeID"),
            scene.by_id(label_maps.at("warped_labels.nii.gz")->ref("display"))->at("colorNodeID"));
  bool confidence = false;
  for (const Node* v : scene.tagged("Volume"))
    confidence |= scene.by_id(v->ref("storage"))->at("fileName") == "segmentation_confidence.nii.gz";
  EXPECT_TRUE(confidence);
}

// The uncertainty map is 0 where no answer is claimed: shown transparent
// there, never as the colour scale's lowest ("most certain") colour.
TEST_F(SlicerScene, TheUncertaintyMapIsTransparentWhereNoAnswerIsClaimed) {
  write_slicer_scene(dir, contents);
  for (const Node* v : parse(dir / kSceneFile).tagged("Volume")) EXPECT_NE(v->at("name"), "uncertainty (95 % band, mm)");
  touch(dir / "uncertainty.nii.gz");
  write_slicer_scene(dir, contents);
  const Scene scene = parse(dir / kSceneFile);
  const Node* map = nullptr;
  for (const Node* v : scene.tagged("Volume"))
    if (scene.by_id(v->ref("storage"))->at("fileName") == "uncertainty.nii.gz") map = v;
  ASSERT_NE(map, nullptr);
  const Node* display = scene.by_id(map->ref("display"));
  ASSERT_NE(display, nullptr);
  EXPECT_EQ(display->tag, "VolumeDisplay");
  EXPECT_EQ(display->at("colorNodeID"), "vtkMRMLColorTableNodeRainbow");
  EXPECT_EQ(display->at("applyThreshold"), "1");
  EXPECT_EQ(display->at("autoThreshold"), "0");
  const double lower = std::stod(display->at("lowerThreshold"));
  EXPECT_GT(lower, 0.0);
  EXPECT_LT(lower, 0.1);  // far below the smallest claimed band (the quantisation, ~0.3 mm)
  EXPECT_GT(std::stod(display->at("upperThreshold")), 1e3);
}

TEST_F(SlicerScene, MissingFilesAreNamed) {
  fs::remove(dir / "field.h5");
  try {
    write_slicer_scene(dir, contents);
    FAIL() << "no error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("field.h5"), std::string::npos) << e.what();
  }
  touch(dir / "field.h5");
  contents.preop_image = "nowhere.nii.gz";
  EXPECT_THROW(write_slicer_scene(dir, contents), std::runtime_error);
}

}  // namespace
}  // namespace brainshift::cli
