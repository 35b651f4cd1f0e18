#include "slicer_scene.h"

#include <cstdio>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "protocol/result_outputs.h"

namespace brainshift::cli {
namespace fs = std::filesystem;
namespace {

std::string xml_escaped(const std::string& s) {
  std::string out;
  for (char c : s) {
    switch (c) {
      case '&': out += "&amp;"; break;
      case '<': out += "&lt;"; break;
      case '>': out += "&gt;"; break;
      case '"': out += "&quot;"; break;
      default: out += c;
    }
  }
  return out;
}

std::string rgb01(const LabelColour& c) {
  char buffer[64];
  std::snprintf(buffer, sizeof buffer, "%.6g %.6g %.6g", c[0] / 255.0, c[1] / 255.0, c[2] / 255.0);
  return buffer;
}

// One MRML element: <Tag id="..." name="..." attr="..."></Tag>.
class Element {
 public:
  Element(std::string tag, std::string id) : tag_(std::move(tag)) { attr("id", std::move(id)); }
  Element& attr(const std::string& key, const std::string& value) {
    text_ += " " + key + "=\"" + xml_escaped(value) + "\"";
    return *this;
  }
  std::string str() const { return " <" + tag_ + text_ + "></" + tag_ + ">\n"; }

 private:
  std::string tag_, text_;
};

void require(const fs::path& dir, const std::string& file) {
  if (!fs::is_regular_file(dir / file))
    throw std::runtime_error((dir / file).string() + ": missing, the Slicer scene needs it");
}

class SceneWriter {
 public:
  std::string storage(const std::string& tag, const std::string& file, const char* coordinate_system = nullptr) {
    const std::string id = "vtkMRML" + tag + "Node" + std::to_string(++count_);
    Element e(tag, id);
    e.attr("name", tag).attr("hideFromEditors", "true").attr("fileName", file).attr("useCompression", "1");
    if (coordinate_system) e.attr("coordinateSystem", coordinate_system);
    xml_ += e.str();
    return id;
  }

  // A scalar or label volume; transform_id empty for the world frame.
  // shown_from > 0: values below it are transparent (Slicer's display
  // threshold), for a map whose 0 means "nothing claimed here".
  void volume(const std::string& file, const std::string& name, bool label_map, const std::string& transform_id,
              const std::string& colour_id, double shown_from = 0) {
    const std::string storage_id = storage("VolumeArchetypeStorage", file);
    const std::string display_tag = label_map ? "LabelMapVolumeDisplay" : "VolumeDisplay";
    const std::string display_id =
        std::string(label_map ? "vtkMRMLLabelMapVolumeDisplayNode" : "vtkMRMLScalarVolumeDisplayNode") +
        std::to_string(++count_);
    Element display(display_tag, display_id);
    display.attr("name", display_tag).attr("hideFromEditors", "true").attr("colorNodeID", colour_id);
    if (!label_map) display.attr("autoWindowLevel", "1");
    if (shown_from > 0)
      display.attr("applyThreshold", "1").attr("autoThreshold", "0").attr("lowerThreshold", std::to_string(shown_from))
          .attr("upperThreshold", "1e+30");
    xml_ += display.str();
    const std::string tag = label_map ? "LabelMapVolume" : "Volume";
    Element v(tag, std::string(label_map ? "vtkMRMLLabelMapVolumeNode" : "vtkMRMLScalarVolumeNode") +
                       std::to_string(++count_));
    std::string refs = "display:" + display_id + ";storage:" + storage_id + ";";
    if (!transform_id.empty()) refs += "transform:" + transform_id + ";";
    v.attr("name", name).attr("references", refs);
    xml_ += v.str();
  }

  void model(const SceneLabel& label) {
    const std::string file = protocol::model_file_name(label.name);
    const std::string storage_id = storage("ModelStorage", file, "RAS");
    const std::string display_id = "vtkMRMLModelDisplayNode" + std::to_string(++count_);
    Element display("ModelDisplay", display_id);
    display.attr("name", "ModelDisplay").attr("hideFromEditors", "true").attr("color", rgb01(label.colour));
    // The brain surface encloses the others: see-through, so they show.
    display.attr("opacity", label.outer ? "0.3" : "1").attr("visibility", "true").attr("visibility2D", "true");
    xml_ += display.str();
    Element m("Model", "vtkMRMLModelNode" + std::to_string(++count_));
    m.attr("name", label.name).attr("references", "display:" + display_id + ";storage:" + storage_id + ";");
    xml_ += m.str();
  }

  std::string grid_transform(const std::string& file) {
    const std::string storage_id = storage("TransformStorage", file);
    const std::string id = "vtkMRMLGridTransformNode" + std::to_string(++count_);
    Element t("GridTransform", id);
    t.attr("name", "brainshift field (resampling: intraop to preop)")
        .attr("references", "storage:" + storage_id + ";");
    xml_ += t.str();
    return id;
  }

  std::string colour_table(const std::string& file) {
    const std::string storage_id = storage("ColorTableStorage", file);
    const std::string id = "vtkMRMLColorTableNodeBrainshiftLabels";
    Element c("ColorTable", id);
    c.attr("name", "brainshift labels").attr("type", "13")  // vtkMRMLColorTableNode::User
        .attr("references", "storage:" + storage_id + ";");
    xml_ += c.str();
    return id;
  }

  std::string str() const { return "<MRML version=\"Slicer4.4.0\" userTags=\"\">\n" + xml_ + "</MRML>\n"; }

 private:
  std::string xml_;
  int count_ = 0;
};

// Slicer's colour table text format: "value name r g b a", 0..255.
std::string colour_table_text(const std::vector<SceneLabel>& labels) {
  std::ostringstream out;
  out << "# brainshift label table (the daemon's): value name r g b a\n0 background 0 0 0 0\n";
  for (const auto& l : labels)
    out << l.value << ' ' << l.name << ' ' << int(l.colour[0]) << ' ' << int(l.colour[1]) << ' ' << int(l.colour[2])
        << " 255\n";
  return out.str();
}

void write_text(const fs::path& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary);
  out << text;
  if (!out) throw std::runtime_error(path.string() + ": cannot write");
}

}  // namespace

void write_slicer_scene(const fs::path& dir, const SceneContents& c) {
  using protocol::ResultPart;
  const std::string field_h5 =
      c.nrrd ? "field.nrrd" : std::string(protocol::result_output(ResultPart::kDisplacementItk).file);
  const std::string warped_image =
      c.nrrd ? "warped_image.nrrd" : std::string(protocol::result_output(ResultPart::kWarpedImage).file);
  const std::string warped_labels =
      c.nrrd ? "warped_labels.nrrd" : std::string(protocol::result_output(ResultPart::kWarpedLabels).file);
  for (const auto& f : {field_h5, warped_image, warped_labels}) require(dir, f);
  if (c.preop_image) require(dir, *c.preop_image);
  if (c.intraop_image) require(dir, *c.intraop_image);
  SceneWriter scene;
  const std::string grey = "vtkMRMLColorTableNodeGrey";  // one of Slicer's built-in tables
  const std::string field = scene.grid_transform(field_h5);
  if (c.preop_image) scene.volume(*c.preop_image, "preop T1 (under the brainshift field)", false, field, grey);
  if (c.intraop_image) scene.volume(*c.intraop_image, "intraop T1", false, "", grey);
  scene.volume(warped_image, "warped preop T1", false, "", grey);
  const std::string labels = scene.colour_table(kSceneColourTable);
  scene.volume(warped_labels, "warped preop labels", true, "", labels);
  // Present when the engine segmented the image itself (an image alone, or
  // labels refined by their image).
  const std::string intraop_labels(protocol::result_output(ResultPart::kIntraopLabels).file);
  const std::string confidence(protocol::result_output(ResultPart::kSegmentationConfidence).file);
  if (fs::is_regular_file(dir / intraop_labels))
    scene.volume(intraop_labels, "intraop labels (automatic segmentation)", true, "", labels);
  if (fs::is_regular_file(dir / confidence))
    scene.volume(confidence, "segmentation confidence (posterior)", false, "", grey);
  // Made after the answer: listed when it is there.
  const std::string uncertainty(protocol::result_output(ResultPart::kUncertainty).file);
  if (fs::is_regular_file(dir / uncertainty))
    // 0 is where no answer is claimed: transparent, so that it is not read
    // as the rainbow's "most certain" blue (the band is never below the
    // segmentation's quantisation, some 0.3 mm, where it is claimed).
    scene.volume(uncertainty, "uncertainty (95 % band, mm)", false, "", "vtkMRMLColorTableNodeRainbow", 0.001);
  for (const auto& l : c.labels)
    if (fs::is_regular_file(dir / protocol::model_file_name(l.name))) scene.model(l);
  write_text(dir / kSceneColourTable, colour_table_text(c.labels));
  write_text(dir / kSceneFile, scene.str());
}

}  // namespace brainshift::cli
